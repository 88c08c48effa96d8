"""Geometry of one's own in front of the demo camera: usda text for tests/usd/test_read_geometry.py and
tests/system/test_user_layer_geometry.py.

`in_view(camera_matrix, *prims)` wraps prim specs in `over "World"` and an Xform `/World/UserGeom`
that carries the camera's world matrix, so its children are placed in the camera's frame (x right,
y up, looking down -z: (0, 0, -5) is 5 m straight ahead). `prim(kind, name, at, *props)` is one prim
spec translated to `at` in that frame.
"""

from __future__ import annotations

import numpy as np

USER = "/World/UserGeom"


def _matrix(m: np.ndarray) -> str:
    """A column-vector 4x4 as usda's matrix4d (USD's row-vector convention: the transpose)."""
    return "(" + ", ".join("(" + ", ".join(f"{v:.17g}" for v in row) + ")" for row in np.asarray(m).T) + ")"


def prim(kind: str, name: str, at=(0.0, 0.0, -5.0), *props: str, meta: str = "", children: str = "") -> str:
    lines = [*props]
    if at is not None:
        lines += [f"double3 xformOp:translate = ({at[0]:g}, {at[1]:g}, {at[2]:g})",
                  'uniform token[] xformOpOrder = ["xformOp:translate"]']
    head = f'def {kind} "{name}"' if kind else f'def "{name}"'
    return f"{head}{f' ({meta})' if meta else ''}\n{{\n" + "\n".join(lines) + "\n" + children + "}\n"


def in_view(camera_matrix: np.ndarray, *prims: str, extra: str = "", label: str | None = None) -> str:
    """`prims` under /World/UserGeom, in the camera's frame; `extra`: more specs under /World; `label`:
    a class for /World/UserGeom (UsdSemantics.LabelsAPI, semantics:labels:class), which its prims inherit."""
    meta = ' (\n        prepend apiSchemas = ["SemanticsLabelsAPI:class"]\n    )' if label else ""
    attr = f'        token[] semantics:labels:class = ["{label}"]\n' if label else ""
    return (f'over "World"\n{{\n    def Xform "UserGeom"{meta}\n    {{\n        matrix4d xformOp:transform = '
            f'{_matrix(camera_matrix)}\n        uniform token[] xformOpOrder = ["xformOp:transform"]\n{attr}'
            + "".join(prims) + "    }\n" + extra + "}\n")
