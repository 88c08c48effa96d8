#!/usr/bin/env python
"""Write the adversarial corpus: malformed, hostile and extreme scene layers, plans, render records
and command lines, each with the outcome the tool must give (tests/system/test_adversarial.py runs them).

    python -m tests.support.adversarial_corpus OUT      # from the repository's root: writes OUT/, one line per case

`make_corpus(out_dir, base=None, spec=None)` returns the cases; `base` is the base stage the good
layers sit on (default: a tiny one built under OUT/stages from tests/support/helpers.py) and `spec(seed,
scene_id, anomaly)` makes a good SceneSpec (default: tests.support.helpers.make_spec at 64x36, 2 samples).
Nothing here costs disk: the 2 GB layers are sparse (os.truncate).

Layout under OUT (the test renders each folder as one run):

    outside/      files no layer may reach; each holds the canary string (CANARY_FILE names it)
    pool/         good_N.usda and the layer-level cases; pool/.sub/ (hidden, so not scanned as
                  scenes) holds their hostile sublayers and textures: a FIFO, links to /etc/passwd,
                  /proc/self/environ and /dev/zero, a 2 GB sparse layer, a text file named .png
    scan/         hostile files the directory scan itself meets: a FIFO p.usda, links to
                  /dev/zero, /etc/passwd and /proc/self/environ named .usda, a 2 GB sparse .usda
    plantree/     plan.toml at its top, private/secret.usda, and scenes/x/plan_escape.usda
                  sublayering it (an ancestor plan.toml must not open the tree to a layer)
    names_mask/   a.usda and a_mask.usda (a's mask and a_mask's image would both be a_mask.png)
    names_case/   Sc.usda and sc.usda
    resume/       a scene over a shared sky/d000.usda (the test edits the sun, then re-renders)
    plans/        hostile plan files (alias bomb, binary, far dates, absurd sizes, a 1e9-scene plan, a YAML
                  key given twice); plans/poses/ their hostile pose files (a FIFO, links to /dev/zero,
                  /proc/self/environ and /proc/self/mounts, deep JSON)
    linktree/     plan.toml, hazards -> ../outside, and scenes/x/hazard_link.usda reading through it
    dataset/      render records: a split "../../escaped", files naming /etc/hostname, an empty folder,
                  r0.json as a FIFO, a link to /dev/zero, nested 100,000 deep, 2 GB sparse; and the
                  renders of datasets (dataset_out/cache_*, manifest_index_*) assembled here whose
                  annotations/records.json or manifest.csv is then edited, replaced or made hostile
    cli/          a file given as --out, a .usdc layer
    install/      locks of two real entries of requirements.lock (idna, setuptools) with idna's hashes
                  altered, and a tiny project: `make env` with VENV, LOCK and PROJECT set to them (the
                  lock's wheel hash is found with `pip download`: writing the corpus reads the index)
"""

from __future__ import annotations

import os
import re
import zlib
from dataclasses import dataclass, field
from pathlib import Path


# Outcomes (what the tool must do with a case)
LAYER_ERROR = "fails as layer error"          # one row in failed.jsonl, kind "layer", attempts 1
TIMEOUT = "fails as timeout"                  # one row in failed.jsonl naming the per-task timeout
FAILS = "fails as layer error or timeout"     # either of the two, never a hang nor a retried crash
CLI_ERROR = "cli exit 2 one line"             # exit status 2, stderr one line "error: ..."
CLI_OK_OR_ERROR = "exit 0 or cli exit 2 one line"
CLI_REFUSED = "cli exit 1, one note line naming the refused record"  # the rest assembled, like render's failures
INSTALL_REFUSED = "make env fails, its last line naming the package and the fix"  # and no stamp is left
RENDERS = "renders"                           # outputs byte-identical to a clean run
REFUSED_OR_DISTINCT = "refused, or renders with distinct outputs"
RERENDERED = "re-rendered, not skipped"

CANARY_FILE = "canary.txt"   # OUT/canary.txt: the unique string the outside files hold
CANARY_ENV = "ALLO_ADVERSARIAL_CANARY"  # the test puts the canary in the environment too (/proc/self/environ)
SPARSE_BYTES = 2 * 1024 ** 3


@dataclass(frozen=True)
class Case:
    name: str                   # unique; for layers, the layer's stem (so its failed.jsonl row's "scene")
    cls: str                    # sandbox, malformed, extreme, hang, names, resume, plan, dataset, cli, good
    expect: str                 # one of the outcomes above
    run: str                    # which run meets it: pool, scan, single, names, resume, plan, dataset, cli
    paths: tuple[Path, ...]     # the case's files (the layer first)
    argv: tuple[str, ...] = ()  # for plan, dataset and cli cases: the arguments after `allo-usd`; install: after `make`
    note: str = ""
    forbidden: tuple[Path, ...] = field(default=())  # paths no process may open for this case
    before: tuple[str, ...] = ()  # install cases: a `make` run (that must succeed) into the same venv first


# ---------------------------------------------------------------- layer text surgery

WORLD_OPEN = re.compile(r'(over "World" \([^)]*\)\n\{\n)')
CAMERA_OPEN = re.compile(r'(over "Camera"\n    \{\n)')
MOON_OPEN = re.compile(r'(over "Moon"\n        \{\n)')
SUBLAYERS = re.compile(r"(subLayers = \[\n)")


def _sub(pattern: re.Pattern | str, repl: str, text: str) -> str:
    out, n = re.subn(pattern, repl, text, count=1)
    if n != 1:
        raise ValueError(f"pattern {pattern!r} not in the template layer")
    return out


def in_world(text: str, body: str) -> str:
    return _sub(WORLD_OPEN, lambda m: m.group(1) + body, text)


def in_camera(text: str, body: str) -> str:
    return _sub(CAMERA_OPEN, lambda m: m.group(1) + body, text)


def with_sublayer(text: str, asset: str) -> str:
    """The layer with `asset` as its strongest sublayer."""
    return _sub(SUBLAYERS, lambda m: m.group(1) + f"        @{asset}@,\n", text)


def moon_texture(text: str, asset: str) -> str:
    over = ('            over "Looks"\n            {\n                over "Regolith"\n                {\n'
            '                    over "BaseColorTexture"\n                    {\n'
            f'                        asset inputs:file = @{asset}@\n                    }}\n                }}\n'
            '            }\n')
    return _sub(MOON_OPEN, lambda m: m.group(1) + over, text)


def mesh(name: str, points: str, counts: str, indices: str) -> str:
    return (f'    def Mesh "{name}"\n    {{\n        int[] faceVertexCounts = {counts}\n'
            f'        int[] faceVertexIndices = {indices}\n        point3f[] points = {points}\n    }}\n\n')


TRIANGLE = "[(0, 0, 0), (1, 0, 0), (0, 1, 0)]"


def canary_layer(canary: str) -> str:
    """A harmless layer that, if composed, puts the canary into the scene's metadata (the render's
    JSON records every allo: attribute of /World) and into the layer's doc."""
    return (f'#usda 1.0\n(\n    doc = "{canary}"\n)\n\nover "World"\n{{\n'
            f'    custom string allo:canary = "{canary}"\n}}\n')


def nested_xforms(depth: int) -> str:
    return "".join(f'def Xform "N{i}" {{\n' for i in range(depth)) + "}\n" * depth


def many_prims(n: int) -> str:
    return '    def Scope "Many"\n    {\n' + "".join(f'        def Xform "P{i}" {{}}\n' for i in range(n)) + "    }\n\n"


def png_bytes(width: int = 8, height: int = 8) -> bytes:
    """A valid grey RGB PNG, written by hand (no image library needed)."""
    import struct

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    raw = b"".join(b"\x00" + b"\x80" * (3 * width) for _ in range(height))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


# ---------------------------------------------------------------- defaults (tiny base, test specs)

def _tests_helpers():
    from tests.support import helpers

    return helpers


def default_spec(seed: int, scene_id: str, anomaly: bool):
    return _tests_helpers().make_spec(seed=seed, scene_id=scene_id, anomaly=anomaly, samples=2)


def default_base(root: Path) -> Path:
    """The tests' tiny base stage (the tiny station and the Crate anomaly), built under `root`."""
    from allo_usd.assets.bodies import build_bodies
    from allo_usd.core.geometry import look_at
    from allo_usd.scene.spec import CameraPose
    from allo_usd.usd.base_stage import write_base_stage

    h = _tests_helpers()
    poses = [CameraPose(i, "train" if i <= 40 else "test", h.CAM_POS + [0, i * 0.1, 0],
                        look_at(h.CAM_POS + [0, i * 0.1, 0], [0, 0, 0])) for i in (1, 2, 41)]
    return write_base_stage(root, h.tiny_station(), build_bodies(), h.tiny_anomalies(), poses)


# ---------------------------------------------------------------- the corpus

class _Writer:
    def __init__(self, out: Path, base: Path, spec):
        self.out, self.base, self.spec = out, base, spec
        self.cases: list[Case] = []
        self._seed = 100

    def layer(self, path: Path, scene_id: str | None = None, anomaly: bool = False) -> str:
        """A good layer written at `path` (its relative paths fit its folder); returns its text."""
        from allo_usd.usd.scene_layer import write_scene_layer

        self._seed += 1
        write_scene_layer(self.spec(self._seed, scene_id or path.stem, anomaly), path, self.base)
        return path.read_text()

    def bad(self, folder: Path, name: str, cls: str, expect: str, mutate, run: str = "pool", anomaly=False,
            note: str = "", extra: tuple = (), forbidden: tuple = ()) -> Path:
        path = folder / f"{name}.usda"
        text = self.layer(path, anomaly=anomaly)
        data = mutate(text)
        if isinstance(data, str):
            data = data.encode()
        path.write_bytes(data)
        self.cases.append(Case(name, cls, expect, run, (path, *extra), note=note, forbidden=tuple(forbidden)))
        return path

    def add(self, *args, **kwargs) -> None:
        self.cases.append(Case(*args, **kwargs))


def make_corpus(out_dir, base: Path | None = None, spec=None, canary: str | None = None) -> list[Case]:
    """Write the corpus under out_dir (which should be empty) and return its cases."""
    import uuid

    from allo_usd.usd.tree import HAZARD_DIR, SCENE_DIR, TREE_PLAN

    out = Path(out_dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    canary = canary or f"ALLO-CANARY-{uuid.uuid4().hex}"
    (out / CANARY_FILE).write_text(canary)
    base = Path(base) if base is not None else default_base(out / "stages")
    w = _Writer(out, base, spec or default_spec)

    outside = out / "outside"
    outside.mkdir(exist_ok=True)
    secret = outside / "secret.usda"
    secret.write_text(canary_layer(canary))
    secret_asset = outside / "secret_asset.usda"
    secret_asset.write_text(canary_layer(canary).replace('over "World"', 'def Xform "World"')
                            .replace("(\n    doc", '(\n    defaultPrim = "World"\n    doc'))
    outside_tex = outside / "tex.png"
    outside_tex.write_bytes(png_bytes() + canary.encode())

    pool = out / "pool"
    sub = pool / ".sub"
    sub.mkdir(parents=True, exist_ok=True)
    for i in range(3):
        path = pool / f"good_{i}.usda"
        w.layer(path, anomaly=i == 1)
        w.add(path.stem, "good", RENDERS, "pool", (path,))

    # ---- sandbox: nothing outside the roots is opened, and the canary never shows
    os.mkfifo(sub / "fifo.usda")
    links = {"passwd": "/etc/passwd", "environ": "/proc/self/environ", "zero": "/dev/zero"}
    for name, target in links.items():
        os.symlink(target, sub / f"{name}.usda")
    with open(sub / "sparse.usda", "wb") as f:
        f.write(b"#usda 1.0\n")
    os.truncate(sub / "sparse.usda", SPARSE_BYTES)
    (sub / "nonimage.png").write_text("this is a text file, not a PNG\n")
    (sub / "truncated.png").write_bytes(png_bytes(64, 64)[:60])
    hostile = tuple(sub / f"{n}.usda" for n in links)

    w.bad(pool, "sub_outside", "sandbox", LAYER_ERROR, lambda t: with_sublayer(t, "../outside/secret.usda"),
          note="sublayer ../outside/secret.usda", forbidden=(secret,))
    w.bad(pool, "sub_abs_outside", "sandbox", LAYER_ERROR, lambda t: with_sublayer(t, str(secret)),
          note="absolute sublayer path outside the roots", forbidden=(secret,))
    for name in links:
        w.bad(pool, f"sub_link_{name}", "sandbox" if name != "zero" else "hang", LAYER_ERROR,
              lambda t, n=name: with_sublayer(t, f"./.sub/{n}.usda"),
              note=f"sublayer: a symlink to {links[name]}", forbidden=hostile)
    w.bad(pool, "sub_abs_environ", "sandbox", LAYER_ERROR, lambda t: with_sublayer(t, "/proc/self/environ"),
          note="sublayer /proc/self/environ by absolute path", forbidden=(Path("/proc/self/environ"),))
    w.bad(pool, "sub_expression", "sandbox", LAYER_ERROR,  # USD evaluates it at open: the walk must refuse it
          lambda t: _sub(SUBLAYERS, lambda m: '    expressionVariables = {\n        string D = "../outside"\n    }\n'
                         + m.group(1) + '        @`"${D}/secret.usda"`@,\n', t),
          note="a sublayer path expression that evaluates outside the roots", forbidden=(secret,))
    w.bad(pool, "tex_expression", "sandbox", LAYER_ERROR, lambda t: moon_texture(t, '`"../outside/tex.png"`'),
          note="a texture path expression that evaluates outside the roots", forbidden=(outside_tex,))
    w.bad(pool, "tex_outside", "sandbox", LAYER_ERROR, lambda t: moon_texture(t, "../outside/tex.png"),
          note="a texture outside the roots", forbidden=(outside_tex,))
    variant = ('    def Xform "Evil" (\n        variants = {{\n            string pick = "a"\n        }}\n'
               '        prepend variantSets = "pick"\n    )\n    {{\n        variantSet "pick" = {{\n'
               '            "a" (\n                prepend {arc} = @../outside/secret_asset.usda@\n            ) {{\n'
               '            }}\n        }}\n    }}\n\n')
    for arc in ("references", "payload"):
        w.bad(pool, f"variant_{arc}_outside", "sandbox", LAYER_ERROR,
              lambda t, a=arc: in_world(t, variant.format(arc=a)), note=f"{arc} inside a variant, outside the roots",
              forbidden=(secret_asset,))
    w.bad(pool, "sub_self_cycle", "sandbox", LAYER_ERROR, lambda t: with_sublayer(t, "./sub_self_cycle.usda"),
          note="the layer sublayers itself")
    w.bad(pool, "sub_directory", "sandbox", LAYER_ERROR, lambda t: with_sublayer(t, "./.sub"),
          note="a directory as sublayer")

    # ---- hang: a reader that blocks or never ends
    w.bad(pool, "sub_fifo", "hang", FAILS, lambda t: with_sublayer(t, "./.sub/fifo.usda"),
          note="a FIFO sublayer (open() blocks until a writer comes)", forbidden=(sub / "fifo.usda",))
    w.bad(pool, "sub_sparse", "hang", FAILS, lambda t: with_sublayer(t, "./.sub/sparse.usda"),
          note="a 2 GB sparse sublayer")

    # ---- malformed
    w.bad(pool, "syntax_error", "malformed", LAYER_ERROR,
          lambda t: in_world(t, "    float broken = (1, 2,\n    this is { not usda\n"),
          note="the error message keeps file:line:col")
    garbage = bytes((i * 7919 + 13) % 256 for i in range(4096))
    w.bad(pool, "binary_garbage", "malformed", LAYER_ERROR, lambda t: garbage, note="4 KB of binary named .usda")
    w.bad(pool, "default_prim_missing", "malformed", LAYER_ERROR, lambda t: _sub(r'    defaultPrim = "World"\n', "", t))
    w.bad(pool, "default_prim_wrong", "malformed", LAYER_ERROR,
          lambda t: _sub(r'defaultPrim = "World"', 'defaultPrim = "Nowhere"', t))
    w.bad(pool, "metallic_string", "malformed", LAYER_ERROR, lambda t: in_world(
        t, '    over "Station"\n    {\n        over "Looks"\n        {\n            over "metal"\n            {\n'
           '                over "PreviewSurface"\n                {\n'
           '                    string inputs:metallic = "shiny"\n                }\n            }\n        }\n'
           '    }\n\n'), note='string inputs:metallic = "shiny"')
    w.bad(pool, "mesh_negative_count", "malformed", LAYER_ERROR,
          lambda t: in_world(t, mesh("Bad", TRIANGLE, "[-3]", "[0, 1, 2]")))
    w.bad(pool, "mesh_index_range", "malformed", LAYER_ERROR,
          lambda t: in_world(t, mesh("Bad", TRIANGLE, "[3]", "[0, 1, 99]")))
    w.bad(pool, "mesh_empty", "malformed", LAYER_ERROR, lambda t: in_world(t, mesh("Bad", "[]", "[]", "[]")))
    w.bad(pool, "mesh_nan_points", "malformed", LAYER_ERROR,
          lambda t: in_world(t, mesh("Bad", "[(0, 0, 0), (nan, 0, 0), (0, 1, 0)]", "[3]", "[0, 1, 2]")))
    w.bad(pool, "quat_zero", "malformed", LAYER_ERROR,
          lambda t: _sub(r"(over \"Camera\"\n    \{\n(?:        [^\n]*\n)*?        quatd xformOp:orient = )\([^)]*\)",
                         r"\1(0, 0, 0, 0)", t))

    # ---- extreme values
    w.bad(pool, "clip_nan", "extreme", LAYER_ERROR, lambda t: in_camera(t, "        float2 clippingRange = (nan, nan)\n"))
    scale0 = ('        double3 xformOp:scale = (0, 0, 0)\n'
              '        uniform token[] xformOpOrder = ["xformOp:translate", "xformOp:orient", "xformOp:scale"]\n')
    w.bad(pool, "camera_zero_scale", "extreme", LAYER_ERROR, lambda t: in_camera(t, scale0))
    w.bad(pool, "mesh_zero_scale", "extreme", LAYER_ERROR, lambda t: in_world(
        t, '    over "Station"\n    {\n        double3 xformOp:scale = (0, 0, 0)\n'
           '        uniform token[] xformOpOrder = ["xformOp:scale"]\n    }\n\n'))
    w.bad(pool, "focal_tiny", "extreme", LAYER_ERROR, lambda t: in_camera(t, "        float focalLength = 1e-30\n"))
    w.bad(pool, "focal_huge", "extreme", LAYER_ERROR, lambda t: in_camera(t, "        float focalLength = 1e30\n"))
    w.bad(pool, "tex_nonimage", "extreme", LAYER_ERROR, lambda t: moon_texture(t, "./.sub/nonimage.png"),
          note="a text file named .png")
    w.bad(pool, "tex_truncated", "extreme", LAYER_ERROR, lambda t: moon_texture(t, "./.sub/truncated.png"))
    w.bad(pool, "tex_missing", "extreme", LAYER_ERROR, lambda t: moon_texture(t, "./.sub/missing.png"))
    w.bad(pool, "nested_10k", "extreme", LAYER_ERROR, lambda t: t + "\n" + nested_xforms(10_000),
          note="10,000 nested Xforms: a depth error, fast")
    w.bad(pool, "prims_300k", "extreme", FAILS, lambda t: in_world(t, many_prims(300_000)),
          note="300,000 prims")
    res = r"uniform int2 resolution = \(\d+, \d+\)"
    w.bad(pool, "resolution_zero", "extreme", LAYER_ERROR, lambda t: _sub(res, "uniform int2 resolution = (0, 0)", t))
    w.bad(pool, "resolution_huge", "extreme", LAYER_ERROR,
          lambda t: _sub(res, "uniform int2 resolution = (2000000000, 2000000000)", t))
    # the target mode's attributes (allo:render:targetPsnr, timeLimit): NaN, out of range, not numbers, a time
    # limit without a target; each one line naming the attribute, before Blender starts
    for name, lines in (("target_nan", "float allo:render:targetPsnr = nan"),
                        ("target_negative", "float allo:render:targetPsnr = -40"),
                        ("target_huge", "float allo:render:targetPsnr = 1e9"),
                        ("target_string", 'string allo:render:targetPsnr = "forty"'),
                        ("time_limit_inf", "float allo:render:targetPsnr = 40\n        float allo:render:timeLimit = inf"),
                        ("time_limit_string", 'float allo:render:targetPsnr = 40\n        string allo:render:timeLimit = "1h"'),
                        ("time_limit_without_target", "float allo:render:timeLimit = 60")):
        w.bad(pool, name, "extreme", LAYER_ERROR,
              lambda t, lines=lines: _sub(res, lambda m: m.group(0) + "\n        " + lines, t))

    # ---- scan: hostile files the directory walk meets before any worker
    scan = out / "scan"
    scan.mkdir()
    w.layer(scan / "scan_good.usda")
    w.add("scan_good", "good", RENDERS, "scan", (scan / "scan_good.usda",))
    os.mkfifo(scan / "p.usda")
    w.add("p", "hang", FAILS, "scan", (scan / "p.usda",), note="a FIFO named p.usda in the render folder",
          forbidden=(scan / "p.usda",))
    for name, target in links.items():
        os.symlink(target, scan / f"{name}.usda")
        w.add(name, "sandbox" if name != "zero" else "hang", LAYER_ERROR, "scan", (scan / f"{name}.usda",),
              note=f"{name}.usda in the render folder: a symlink to {target}", forbidden=(scan / f"{name}.usda",))
    with open(scan / "big.usda", "wb") as f:
        f.write(b'#usda 1.0\n(\n    customLayerData = {\n        dictionary allo = {\n'
                b'            string sceneId = "big"\n        }\n    }\n)\n')
    os.truncate(scan / "big.usda", SPARSE_BYTES)
    w.add("big", "hang", FAILS, "scan", (scan / "big.usda",), note="a 2 GB sparse scene layer")

    # ---- an ancestor plan.toml does not open its tree to a layer below it
    tree = out / "plantree"
    (tree / "private").mkdir(parents=True)
    (tree / TREE_PLAN).write_text('name = "hostile"\n')
    (tree / "private" / "secret.usda").write_text(canary_layer(canary))
    folder = tree / SCENE_DIR / "x"
    folder.mkdir(parents=True)
    layer = w.bad(folder, "plan_escape", "sandbox", CLI_ERROR,
                  lambda t: with_sublayer(t, "../../private/secret.usda"), run="single",
                  note="sublayers plantree/private/secret.usda; plantree/plan.toml must not grant it",
                  forbidden=(tree / "private" / "secret.usda",))
    w.cases[-1] = Case(**{**w.cases[-1].__dict__, "argv": ("render", str(layer))})

    # ---- a tree's own folder linked out of it grants nothing: hazards/ -> outside/
    tree = out / "linktree"
    tree.mkdir()
    (tree / TREE_PLAN).write_text('name = "hostile"\n')
    os.symlink(outside, tree / HAZARD_DIR)
    folder = tree / SCENE_DIR / "x"
    folder.mkdir(parents=True)
    layer = w.bad(folder, "hazard_link", "sandbox", CLI_ERROR,
                  lambda t: with_sublayer(t, "../../hazards/secret.usda"), run="single",
                  note="linktree/hazards is a link to outside/; the layer sublayers hazards/secret.usda",
                  forbidden=(secret,))
    w.cases[-1] = Case(**{**w.cases[-1].__dict__, "argv": ("render", str(layer))})

    # ---- names whose outputs would collide
    for folder_name, stems in (("names_mask", ("a", "a_mask")), ("names_case", ("Sc", "sc"))):
        d = out / folder_name
        d.mkdir()
        paths = []
        for stem in stems:
            w.layer(d / f"{stem}.usda")
            paths.append(d / f"{stem}.usda")
        w.add(folder_name, "names", REFUSED_OR_DISTINCT, "names", tuple(paths),
              note=f"{' and '.join(s + '.usda' for s in stems)} in one folder")

    # ---- a shared sublayer edited after rendering: the scene is rendered again
    d = out / "resume"
    (d / "sky").mkdir(parents=True)
    text = w.layer(d / "scene.usda")
    sun = re.compile(r'(over "SunLight"\n        \{\n(?:.*\n)*?)            float inputs:intensity = \S+\n')
    (d / "scene.usda").write_text(with_sublayer(_sub(sun, r"\1", text), "./sky/d000.usda"))
    (d / "sky" / "d000.usda").write_text('#usda 1.0\n\nover "World"\n{\n    over "Sky"\n    {\n'
                                         '        over "SunLight"\n        {\n'
                                         '            float inputs:intensity = 1361\n        }\n    }\n}\n')
    w.add("stale_resume", "resume", RERENDERED, "resume", (d / "scene.usda", d / "sky" / "d000.usda"),
          note="render, set the shared sky layer's sun intensity to 0, render again")

    # ---- plans: one line, exit 2, fast, bounded memory
    plans = out / "plans"
    plans.mkdir()
    good = ('name = "hostile"\nseeds = [1]\n\n[dates]\nstart = "2030-01-01"\ndays = 1\nstep_days = 1\n\n'
            '[poses]\ntrain = [1]\ntest = []\n\n[anomalies]\nassets = []\n\n'
            '[quality]\npreset = "draft"\nresolution = [64, 36]\nsamples = 1\n')

    def plan(name: str, data: str | bytes, note: str, expect: str = CLI_ERROR, suffix: str = ".toml",
             limit: bool = True) -> None:
        path = plans / f"{name}{suffix}"
        path.write_bytes(data if isinstance(data, bytes) else data.encode())
        argv = ("author", str(path), "--out", str(out / "plan_out" / name), "--no-progress")
        w.add(f"plan_{name}", "plan", expect, "plan", (path,), argv + (("--limit", "1") if limit else ()), note)

    levels = ["a: &a [1, 1, 1, 1, 1, 1, 1, 1, 1]"] + [
        f"{chr(98 + i)}: &{chr(98 + i)} [" + ", ".join([f"*{chr(97 + i)}"] * 9) + "]" for i in range(9)]
    plan("alias_bomb", "name: bomb\n" + "\n".join(levels) + "\nseeds: *j\n", "YAML billion laughs", suffix=".yaml")
    plan("binary", bytes((i * 131 + 7) % 256 for i in range(2048)), "binary bytes named .toml")
    plan("far_start", good.replace('start = "2030-01-01"', 'start = "9999-12-31"'), "start 9999-12-31")
    plan("days_1e9", good.replace("\ndays = 1\n", "\ndays = 1000000000\n"), "days 1e9")
    plan("step_1e11", good.replace("\ndays = 1\n", "\ndays = 2\n").replace("step_days = 1", "step_days = 100000000000"),
         "step_days 1e11")
    plan("unknown_preset", good.replace('preset = "draft"', 'preset = "ultra-mega"'), "an unknown quality preset")
    plan("yaml_duplicate_key", "name: hostile\nseeds: [1]\nquality:\n  preset: draft\n  samples: 3\n  samples: 2\n",
         "a YAML plan giving quality.samples twice (refused as TOML refuses it)", suffix=".yaml")
    huge = (good.replace('start = "2030-01-01"', 'start = "1900-01-01"').replace("\ndays = 1\n", "\ndays = 50000\n")
            .replace("seeds = [1]", "seeds = [" + ", ".join(map(str, range(400))) + "]")
            .replace("train = [1]\ntest = []", "train = [" + ", ".join(map(str, range(1, 41))) + "]\n"
                     "test = [" + ", ".join(map(str, range(41, 51))) + "]")
            .replace("assets = []\n", ""))
    plan("scenes_1e9", huge, "a schema-valid plan of ~2e9 scenes, authored with --limit 1 (no hang, bounded memory)",
         expect=CLI_OK_OR_ERROR)
    big = plans / "oversize.toml"
    with open(big, "w") as f:  # valid TOML (a comment), 64 MB on disk: a plan is a few KB
        f.write(good)
        line = "# " + "x" * 1022 + "\n"
        f.write(line * (64 * 1024))
    w.add("plan_oversize", "plan", CLI_ERROR, "plan", (big,),
          ("author", str(big), "--out", str(out / "plan_out" / "oversize"), "--no-progress", "--limit", "1"),
          "a 64 MB plan file (valid TOML)")

    # ---- plans whose pose file is hostile: the read gate refuses it unopened / unparsed
    poses = plans / "poses"
    poses.mkdir()
    os.mkfifo(poses / "fifo.csv")
    os.symlink("/dev/zero", poses / "zero.csv")
    os.symlink("/proc/self/environ", poses / "environ.csv")   # the environment holds the canary (CANARY_ENV)
    os.symlink("/proc/self/mounts", poses / "mounts.csv")
    (poses / "deep.json").write_text('[{"name": "a", "split": "train", "position": ' + "[" * 100_000 +
                                     "]" * 100_000 + "}]\n")
    for name, note, unopened in (("fifo.csv", "a FIFO as poses.file", True),
                                 ("zero.csv", "poses.file linked to /dev/zero", True),
                                 ("environ.csv", "poses.file linked to /proc/self/environ (a pseudo-file: the "
                                  "environment must not reach the message)", True),
                                 ("mounts.csv", "poses.file linked to /proc/self/mounts (a pseudo-file)", True),
                                 ("deep.json", "a pose JSON nested 100,000 deep", False)):
        path = plans / f"poses_{Path(name).stem}.toml"
        path.write_text(good.replace("[poses]\n", f'[poses]\nfile = "{poses / name}"\n'))
        w.add(f"plan_poses_{Path(name).stem}", "plan", CLI_ERROR, "plan", (path, poses / name),
              ("author", str(path), "--out", str(out / "plan_out" / f"poses_{Path(name).stem}"), "--no-progress",
               "--limit", "1"), note, forbidden=(poses / name,) if unopened else ())

    # ---- dataset: render records that point outside the dataset
    ds = out / "dataset"
    (ds / "empty").mkdir(parents=True)
    w.add("dataset_empty", "dataset", CLI_ERROR, "dataset", (ds / "empty",),
          ("dataset", str(ds / "empty"), "--out", str(out / "dataset_out" / "empty")), "an empty render folder")
    for name, scene, files in (
            ("escaped_split", {"split": "../../escaped"}, None),
            ("hostname_files", {}, {"rgb": "/etc/hostname", "exr": "/etc/hostname", "mask": "/etc/hostname"})):
        d = ds / name
        d.mkdir()
        _render_record(d, "r0", scene, files)
        w.add(f"dataset_{name}", "dataset", CLI_REFUSED, "dataset", (d,),
              ("dataset", str(d), "--out", str(out / "dataset_out" / name)),
              f"a render JSON with {'split ../../escaped' if scene else 'file names /etc/hostname'}")

    # ---- render records the read gate refuses unopened / unparsed: left out with a note
    for name, make, note in (
            ("fifo_record", lambda f: os.mkfifo(f), "a FIFO named r0.json"),
            ("zero_record", lambda f: os.symlink("/dev/zero", f), "r0.json linked to /dev/zero"),
            ("deep_record", lambda f: f.write_text("[" * 100_000 + "]" * 100_000), "r0.json nested 100,000 deep"),
            ("big_record", lambda f: (f.write_bytes(b"{}"), os.truncate(f, SPARSE_BYTES)),
             "a 2 GB sparse r0.json (too big, not 'no record')")):
        d = ds / name
        d.mkdir()
        make(d / "r0.json")
        w.add(f"dataset_{name}", "dataset", CLI_REFUSED, "dataset", (d / "r0.json",),
              ("dataset", str(d), "--out", str(out / "dataset_out" / name)), note,
              forbidden=(d / "r0.json",) if name in ("fifo_record", "zero_record") else ())

    # ---- the dataset's cache (annotations/records.json) and manifest.csv edited between two runs
    for name, tamper, expect, note in _CACHE_CASES:
        d, made = ds / name, out / "dataset_out" / name
        _cached_dataset(d, made)
        target = tamper(made)
        w.add(f"dataset_{name}", "dataset", expect, "dataset", (target,),
              ("dataset", str(d), "--out", str(made)), note)   # not forbidden: the run writes the cache anew

    # ---- a render JSON naming a hostile anomaly model (BOP's PLY is read from it): a note, no PLY, no hang
    for name, make, note in (
            ("model_fifo", lambda f: os.mkfifo(f), "the anomaly's model file a FIFO"),
            ("model_zero", lambda f: os.symlink("/dev/zero", f), "the anomaly's model linked to /dev/zero"),
            ("model_passwd", lambda f: os.symlink("/etc/passwd", f), "the anomaly's model linked to /etc/passwd"),
            ("model_garbage", lambda f: f.write_bytes(b"#usda 1.0\n(\n" + b"\xff" * 4096), "a model that is not USD")):
        d, made = ds / name, out / "dataset_out" / name
        _cached_dataset(d, made)
        make(d / "m.usda")
        _name_model(d / "a1.json", "m.usda")
        w.add(f"dataset_{name}", "dataset", MODEL_WARNED, "dataset", (d / "m.usda",),
              ("dataset", str(d), "--out", str(made)), note,
              forbidden=(d / "m.usda",) if name in ("model_fifo", "model_zero", "model_passwd") else ())

    # ---- command lines
    cli = out / "cli"
    cli.mkdir()
    (cli / "a_file").write_text("not a directory\n")
    good0 = pool / "good_0.usda"
    w.add("cli_out_is_file", "cli", CLI_ERROR, "cli", (cli / "a_file",),
          ("render", str(good0), "--out", str(cli / "a_file")), "--out names a file")
    w.add("cli_out_readonly", "cli", CLI_ERROR, "cli", (),
          ("render", str(good0), "--out", "/proc/allo-adversarial/out"), "--out in a read-only directory (/proc)")
    w.add("cli_workers_negative", "cli", CLI_ERROR, "cli", (),
          ("render", str(good0), "--out", str(out / "cli_out" / "workers"), "--workers", "-1"), "--workers -1")
    from pxr import Sdf

    usdc = cli / "good.usdc"
    Sdf.Layer.FindOrOpen(str(good0)).Export(str(usdc))
    w.add("cli_usdc", "cli", CLI_OK_OR_ERROR, "cli", (usdc,),
          ("render", str(usdc), "--out", str(out / "cli_out" / "usdc")),
          "render of a .usdc layer")

    # ---- packages: one line each, never USD's exception (a 0-byte package, an --out USD cannot name,
    # a package lacking a texture its layer names)
    empty = cli / "empty.usdz"
    empty.write_bytes(b"")
    for command, args in (("inspect", (str(empty),)),
                          ("render", (str(empty), "--out", str(out / "cli_out" / "empty_usdz"))),
                          ("diff", (str(empty), str(empty)))):
        w.add(f"cli_empty_usdz_{command}", "cli", CLI_ERROR, "cli", (empty,), (command, *args),
              f"{command} of a 0-byte .usdz")
    w.add("cli_pack_out_newline", "cli", CLI_ERROR, "cli", (),
          ("pack", str(good0), "--out", str(out / "cli_out" / "a\nb.usdz")), "pack --out with a newline in the name")
    lacking, scene = cli / "lacking.usdz", cli / "with_texture" / "scene.usda"
    (scene.parent / "moon.png").parent.mkdir()
    (scene.parent / "moon.png").write_bytes(png_bytes())
    scene.write_text(moon_texture(w.layer(scene), "./moon.png"))
    _package_lacking_a_texture(scene, lacking, base)
    w.add("cli_package_lacking_texture", "cli", CLI_ERROR, "cli", (lacking,),
          ("render", str(lacking), "--out", str(out / "cli_out" / "lacking")),
          "a package whose texture entry is missing (fix: pack again, not restore a textures/ folder)")
    # ---- install: `make env` with a tampered requirements.lock fails naming the package, fresh or not
    inst = out / "install"
    (inst / "project").mkdir(parents=True)
    (inst / "project" / "pyproject.toml").write_text(
        '[build-system]\nrequires = ["setuptools>=68"]\nbuild-backend = "setuptools.build_meta"\n\n'
        '[project]\nname = "lockprobe"\nversion = "0"\n\n[tool.setuptools]\npy-modules = []\n')
    pins = lock_pins(Path(__file__).resolve().parents[2] / "requirements.lock")
    idna_version, idna_hashes = pins["idna"]
    wheel = wheel_sha256("idna", idna_version)

    def lock(name: str, idna: list[str]) -> Path:
        path = inst / f"{name}.lock"
        path.write_text(lock_entry("idna", idna_version, idna) + lock_entry("setuptools", *pins["setuptools"]))
        return path

    def make_env(venv: str, lock_file: Path) -> tuple[str, ...]:
        return ("env", f"VENV={inst / venv}", f"LOCK={lock_file}", f"PROJECT={inst / 'project'}")

    alter = lambda h: ("0" if h[0] != "0" else "1") + h[1:]  # noqa: E731
    fresh = lock("wheel_hash", [alter(h) if h == wheel else h for h in idna_hashes])
    w.add("install_fresh_wheel_hash", "install", INSTALL_REFUSED, "install", (fresh,), make_env("fresh", fresh),
          "a fresh venv, idna's wheel hash altered (its source package's kept: no fallback to building it)")
    both = lock("both_hashes", [alter(h) for h in idna_hashes])
    w.add("install_existing_both_hashes", "install", INSTALL_REFUSED, "install", (both,), make_env("existing", both),
          "a venv built from the real entries, then both of idna's hashes altered (not trusted as installed)",
          before=make_env("existing", lock("good", idna_hashes)))
    return w.cases


def _package_lacking_a_texture(scene: Path, dest: Path, base: Path) -> None:
    """`allo-usd pack` of `scene` (a layer over the base stage `base`, whose moon texture is
    moon.png beside it), then the package written again without that texture's entry (USD's own
    zip writer, the others in order)."""
    import zipfile

    from pxr import Sdf

    from allo_usd.usd.pack import pack
    from allo_usd.usd.safety import ENV_ROOTS

    work = scene.parent
    before = os.environ.get(ENV_ROOTS)
    os.environ[ENV_ROOTS] = os.pathsep.join([str(Path(base).parent), *([before] if before else [])])
    try:
        pack(scene, work / "whole.usdz")
    finally:
        if before is None:
            os.environ.pop(ENV_ROOTS, None)
        else:
            os.environ[ENV_ROOTS] = before
    with zipfile.ZipFile(work / "whole.usdz") as zf:
        names = [n for n in zf.namelist() if not n.endswith("moon.png")]
        zf.extractall(work / "entries", names)
    writer = Sdf.ZipFileWriter.CreateNew(str(dest))
    for name in names:
        writer.AddFile(str(work / "entries" / name), name)
    writer.Save()


LOCK_ENTRY = re.compile(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==(\S+) \\\n((?:[ \t]+--hash=sha256:[0-9a-f]{64}[ \t]*\\?\n?)+)", re.M)


def lock_pins(lock: Path) -> dict[str, tuple[str, list[str]]]:
    """{name: (version, sha256 hashes)} of a pip-compile lock."""
    return {m.group(1).lower(): (m.group(2), re.findall(r"[0-9a-f]{64}", m.group(3)))
            for m in LOCK_ENTRY.finditer(lock.read_text())}


def lock_entry(name: str, version: str, hashes: list[str]) -> str:
    return f"{name}=={version} \\\n" + " \\\n".join(f"    --hash=sha256:{h}" for h in hashes) + "\n"


def wheel_sha256(name: str, version: str) -> str:
    """The sha256 of the wheel pip fetches for name==version (a lock also lists its source package's)."""
    import hashlib
    import subprocess
    import sys
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        subprocess.run([sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "--only-binary", ":all:",
                        "-d", d, f"{name}=={version}"], check=True, capture_output=True, timeout=120)
        [whl] = Path(d).glob("*.whl")
        return hashlib.sha256(whl.read_bytes()).hexdigest()


def _render_record(d: Path, name: str, scene: dict, files: dict | None) -> None:
    """A render record as allo_usd.run.job writes it (NAME.json beside a PNG and a mask), with
    `scene` fields and `files` overriding the honest ones."""
    import json

    (d / f"{name}.png").write_bytes(png_bytes(64, 36))
    (d / f"{name}_mask.png").write_bytes(png_bytes(64, 36))
    meta = {"layer": str(d / f"{name}.usda"), "layer_sha256": "0" * 64, "package_version": "0.1.0",
            "render_seconds": 0.1, "resolution": [64, 36],
            "class_pixels": {"background": 2304, "station_and_bodies": 0, "anomaly": 0}, "anomaly_fraction": 0.0,
            "scene": {"sceneId": name, "split": "train", "variant": "normal", "pose": 1, "day": 0, "seed": 1,
                      "seedPath": "1/0/1/1", "provenance": {}, **scene},
            "effects": {}, "files": files or {"rgb": f"{name}.png", "exr": f"{name}.exr", "mask": f"{name}_mask.png"}}
    (d / f"{name}.json").write_text(json.dumps(meta))


def _cached_dataset(d: Path, out: Path) -> None:
    """A dataset assembled in-process from two honest render records (a normal train scene, an
    anomalous test scene with 12 anomaly pixels), so that OUT holds records.json and manifest.csv."""
    import json
    import warnings

    import numpy as np
    from PIL import Image

    from allo_usd.output.dataset import assemble

    d.mkdir(parents=True)
    for name, split, variant in (("r0", "train", "normal"), ("a1", "test", "anomaly")):
        mask = np.ones((36, 64), np.uint8)
        mask[:8] = 0
        if variant == "anomaly":
            mask[10:13, 20:24] = 2
        Image.fromarray(np.full((36, 64, 3), 90, np.uint8)).save(d / f"{name}.png")
        Image.fromarray(mask).save(d / f"{name}_mask.png")
        counts = {"background": int((mask == 0).sum()), "station_and_bodies": int((mask == 1).sum()),
                  "anomaly": int((mask == 2).sum())}
        meta = {"layer": str(d / f"{name}.usda"), "layer_sha256": f"{len(name):064d}", "package_version": "0.1.0",
                "render_seconds": 0.1, "resolution": [64, 36], "class_pixels": counts,
                "anomaly_fraction": counts["anomaly"] / 2304, "effects": {},
                "scene": {"sceneId": name, "split": split, "variant": variant, "pose": 1, "day": 0, "seed": 1,
                          "seedPath": "1/0/1/1", "provenance": {},
                          **({"anomaly": {"asset": "crate", "assetVariant": "blue"}} if variant == "anomaly" else {})},
                "files": {"rgb": f"{name}.png", "exr": f"{name}.exr", "mask": f"{name}_mask.png"}}
        (d / f"{name}.json").write_text(json.dumps(meta))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assemble([d], out)


def _name_model(record: Path, model: str) -> None:
    """The render record's anomaly names `model` (relative to its layer's folder) as its model file, with a
    pose, as a render of a user's layer records them."""
    import json

    meta = json.loads(record.read_text())
    obj = {"path": "/World/Anomaly", "pixels": 12, "model": {"asset": "crate", "variant": "blue", "model_id": "crate/blue",
                                                            "path": model},
           "pose": {"cam_R_m2c": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0], "cam_t_m2c": [0.0, 0.0, 2000.0],
                    "model_units": "m", "model_scale": [1.0, 1.0, 1.0]}}
    meta["annotations"] = {"anomaly": obj, "anomalies": [obj]}
    record.write_text(json.dumps(meta))


def _edit_cache(change):
    """A tamper: records.json parsed, `change(cache, entry of a1)` applied, written back."""
    import json

    def tamper(out: Path) -> Path:
        path = out / "annotations" / "records.json"
        cache = json.loads(path.read_text())
        change(cache, cache["records"]["allo/a1"])
        path.write_text(json.dumps(cache))
        return path
    return tamper


def _replace_cache(make):
    def tamper(out: Path) -> Path:
        path = out / "annotations" / "records.json"
        path.unlink()
        make(path)
        return path
    return tamper


def _manifest_index(value: str):
    def tamper(out: Path) -> Path:
        import csv
        import io

        path = out / "manifest.csv"
        rows = list(csv.DictReader(io.StringIO(path.read_text())))
        rows[0]["index"] = value
        buffer = io.StringIO()
        writer = csv.DictWriter(buffer, fieldnames=list(rows[0]), lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
        path.write_text(buffer.getvalue())
        return path
    return tamper


CACHE_RECOMPUTED = "cli exit 0, notes, one naming records.json"   # the cache recomputed, the dataset assembled
MODEL_WARNED = "cli exit 0, one note naming the BOP model, no PLY of it"   # the rest of the dataset assembled
_CACHE_CASES = (
    ("cache_folder", _edit_cache(lambda c, e: e.update(bop={"folder": "../escaped"}, camera={"INJECTED": "x"})),
     CACHE_RECOMPUTED, "a cached record whose BOP folder is ../escaped (and an injected camera)"),
    ("cache_bbox", _edit_cache(lambda c, e: e["coco"][0].update(bbox=[0, 0, 1, 1])),
     CACHE_RECOMPUTED, "a cached COCO bbox edited to [0, 0, 1, 1]"),
    ("cache_image", _edit_cache(lambda c, e: e.update(image="/etc/passwd")),
     CACHE_RECOMPUTED, "a cached record whose image is /etc/passwd"),
    ("cache_shape", _edit_cache(lambda c, e: e.pop("width")),
     CACHE_RECOMPUTED, "a cached record without a field (its width)"),
    ("cache_bbox_obj", _edit_cache(lambda c, e: e["gt"][0]["info"].update(bbox_obj=[-200, 0, 5, 5], px_count_all=20)),
     CACHE_RECOMPUTED, "a cached BOP bbox_obj off the toolkit's 3W x 3H canvas"),
    ("cache_fifo", _replace_cache(lambda p: os.mkfifo(p)), CACHE_RECOMPUTED, "records.json as a FIFO"),
    ("cache_zero", _replace_cache(lambda p: os.symlink("/dev/zero", p)), CACHE_RECOMPUTED,
     "records.json linked to /dev/zero"),
    ("cache_sparse", _replace_cache(lambda p: (p.write_bytes(b"{}"), os.truncate(p, SPARSE_BYTES))),
     CACHE_RECOMPUTED, "records.json a 2 GB sparse file"),
    ("cache_deep", _replace_cache(lambda p: p.write_text("[" * 200_000 + "]" * 200_000)), CACHE_RECOMPUTED,
     "records.json nested 200,000 deep"),
    ("cache_directory", _replace_cache(lambda p: p.mkdir()), CACHE_RECOMPUTED, "a directory in records.json's place"),
    ("manifest_index_abc", _manifest_index("abc"), CLI_ERROR, "manifest.csv's index abc"),
    ("manifest_index_negative", _manifest_index("-5"), CLI_ERROR, "manifest.csv's index -5"),
    ("manifest_index_huge", _manifest_index("1e30"), CLI_ERROR, "manifest.csv's index 1e30"),
)


def main(argv: list[str] | None = None) -> int:
    import argparse

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("out", type=Path, help="an empty directory to write the corpus into")
    args = p.parse_args(argv)
    for c in make_corpus(args.out):
        print(f"{c.cls:10} {c.name:28} {c.run:8} {c.expect:34} {c.note}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
