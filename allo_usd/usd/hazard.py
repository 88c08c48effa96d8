"""Your own hazards: a plan's model files converted into anomaly assets inside the authored tree.

A plan's anomaly list may name a glTF/GLB, OBJ, STL or USD file next to the built-in ids
(allo_usd.plan.model.AnomalyChoice). When the plan is authored, each such file is converted once:

    OUT/hazards/<id>/<id>.usda               the asset interface (class label anomaly, a `variant` set)
    OUT/hazards/<id>/<id>/<variant>.usdc     one geometry file per variant (+ textures/)
    OUT/hazards/<id>/source.json             what it was made from: file name, sha256, units, up axis,
                                             colours, and for a USD file the sha256 of every other
                                             layer it composes (a re-run checks it; a changed file is
                                             refused); and what came of it (`converted`: triangles
                                             kept and dropped)

Mesh files go through the importer of `allo-usd asset import` (allo_usd.assets.importer, with
the plan's units and up axis, never guessed); a USD file is read with pxr (its meshes with their
world transforms, each mesh's bound UsdPreviewSurface constant colour, metallic and roughness,
else its displayColor), scaled by its metersPerUnit and turned from its upAxis, both of which a
plan may also state (they must then agree with the file). Before USD opens a USD hazard, every
file its composition reads is checked (allo_usd.usd.dependencies.walk_hazard: the rules of a
scene layer, within the hazard's own folder), so a sublayer, reference or payload outside it, a
FIFO, a variable expression or a value clip is refused by name, never read. Either way the
asset is recentred on its bounding-box centre (the placement code takes that as the object's
origin) and must measure 1 cm to 20 m: anything else is almost always a unit mistake.
Variants: `default` keeps the file's materials; each of the plan's `colors` sets every
material's base colour (a texture is multiplied by it). Triangles the conversion drops (a
non-finite vertex, an index outside the points, zero area: allo_usd.assets.importer.
kept_triangles) are counted, and the count is recorded (droppedTriangles in the layer's
provenance, `converted` in source.json). The tree's copy is written to a temporary folder and
renamed, so a killed run leaves nothing half-made, and the same file gives the same bytes
wherever the tree is authored.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import replace
from pathlib import Path

import numpy as np

from allo_usd.core.version import __version__
from allo_usd.assets.mesh import Asset, Material, MeshPart
from allo_usd.core.errors import AlloError, PlanError
from allo_usd.core.files import atomic_directory, file_problem, sha256_file
from allo_usd.plan.model import HAZARD_USD_SUFFIXES, USER_VARIANT
from allo_usd.usd.tree import HAZARD_MARKER, hazard_asset_path, hazard_root
from allo_usd.core import fixedmath as fm

CONVERTED = "converted"               # source.json's record of what the conversion made (not compared)
SIZE_M = (0.01, 20.0)                 # a hazard's largest extent, metres (a tool .. a loose panel)
STATION_SIZE_M = (0.01, 500.0)        # `asset import --label station`: the ISS, the largest built, is 109 m
MAX_TRIANGLES = 2_000_000             # after triangulation (the built-in hazards have < 20k)
MAX_FILE_BYTES = 512 << 20


def made_from(choice) -> dict:
    """What a hazard's conversion depends on (recorded in source.json, compared on every run): for a
    USD file also `composes`, the sha256 of every other layer its composition reads (when there are
    any), so an edit to a sublayer is caught like an edit to the file itself."""
    source = Path(choice.file)
    problem = file_problem(source, MAX_FILE_BYTES)
    if problem:
        if "No such file" in problem:
            problem = "does not exist"
        raise PlanError(f"anomaly {choice.id!r}: file {_short_path(source)} {problem}; fix: give the path of your "
                        "hazard's model file (relative to the working directory), at most "
                        f"{MAX_FILE_BYTES >> 20} MiB (decimate a larger one)")
    out = {"id": choice.id, "source": source.name, "sha256": sha256_file(source), "units": choice.units,
           "up_axis": choice.up_axis, "colors": {k: list(v) for k, v in (choice.colors or {}).items()},
           "variants": list(choice.user_variants())}
    if source.suffix.lower() in HAZARD_USD_SUFFIXES:
        composes = composed_layers(usd_hazard_walk(source, choice.id), source)
        if composes:
            out["composes"] = composes
    return out


def usd_hazard_walk(path: Path, name: str, what: str = "anomaly"):
    """Every file a USD hazard's composition reads, checked before USD opens any of them
    (allo_usd.usd.dependencies.walk_hazard), or a PlanError naming the refused path and the rule.
    Registers the allo-usd schema first: pxr reads schema plugins once, on the first stage."""
    from allo_usd.core.errors import LayerError
    from allo_usd.usd import schema
    from allo_usd.usd.dependencies import walk_hazard

    schema.register()
    try:
        return walk_hazard(path)
    except LayerError as exc:
        raise PlanError(f"{what} {name!r}: {exc}") from None


def composed_layers(walked, source: Path) -> dict[str, str]:
    """{path relative to the hazard's folder: sha256} of every layer `walked` (usd_hazard_walk)
    read besides the hazard file itself (a package is one file: none)."""
    import os

    base = os.path.realpath(os.path.dirname(os.path.abspath(source)))   # where USD anchors its relative paths
    return {os.path.relpath(f, base): sha256_file(Path(f)) for f in walked.layer_files()[1:]}


def _short_path(path: Path) -> str:
    text = str(path)
    return text if len(text) <= 200 else text[:120] + "..." + text[-60:]


def write_hazards(plan, out_dir: Path) -> dict[str, Path]:
    """Convert every user hazard of `plan` into `out_dir/hazards` (once; a later run checks that the
    file and options are the ones the tree's copy was made from). Returns {id: interface layer}."""
    out = {}
    for choice in plan.anomalies.user_hazards():
        want = made_from(choice)
        root = hazard_root(out_dir, choice.id)
        marker, path = root / HAZARD_MARKER, hazard_asset_path(out_dir, choice.id)
        if marker.is_file() and path.is_file():
            from allo_usd.core.files import read_own_record, record_shown

            recorded = read_own_record(marker)   # through the gate: a FIFO or a pseudo-file is no record
            if isinstance(recorded, dict):   # `converted` says what came out, not what it was made from
                recorded = {k: v for k, v in recorded.items() if k != CONVERTED}
            if recorded != want:
                shown = record_shown(recorded, want) or "an unreadable record"   # the record's own fields only
                raise PlanError(f"{root} was made from {shown}, not from {want} "
                                f"(the hazard's file or options changed since its scenes were authored); fix: author "
                                "into a new output directory, or author with --replace")
        else:
            with atomic_directory(root) as tmp:
                _, info = _convert(choice, tmp, want["sha256"])
                converted = {"triangles": info["triangles"], "droppedTriangles": info["droppedTriangles"]}
                (tmp / HAZARD_MARKER).write_text(json.dumps({**want, CONVERTED: converted}, indent=1,
                                                            sort_keys=True) + "\n")
        out[choice.id] = path
    return out


def convert_hazard(choice, directory: Path, sha256: str | None = None) -> Path:
    """Write `choice`'s asset (every variant) into `directory`; returns the interface layer. `sha256`:
    the source file's, if already computed (made_from)."""
    return _convert(choice, directory, sha256)[0]


def _convert(choice, directory: Path, sha256: str | None = None) -> tuple[Path, dict]:
    """convert_hazard, also returning what the conversion used and made (load_hazard's info)."""
    from allo_usd.usd.asset import write_variant_asset

    source = Path(choice.file)
    asset, info = load_hazard(source, choice.id, choice.units, choice.up_axis)
    variants = {name: asset if name == USER_VARIANT else coloured(asset, choice.colors[name])
                for name in choice.user_variants()}
    provenance = {"id": choice.id, "source": source.name, "sha256": sha256 or sha256_file(source), **info,
                  "colors": {k: [float(c) for c in v] for k, v in (choice.colors or {}).items()},
                  "packageVersion": __version__}
    doc = (f"allo-usd hazard {choice.id!r} converted from {source.name} (sha256 {provenance['sha256'][:12]}..., "
           f"unit {info['unit']}, up axis {info['upAxis']})")
    path = write_variant_asset(variants, directory, choice.id, "anomaly", doc=doc,
                               custom={"allo": {"hazard": _layer_data(provenance)}})
    return path, info


def _layer_data(value):
    """A JSON-like value as customLayerData accepts it (number lists as Vt.DoubleArray)."""
    from pxr import Vt

    if isinstance(value, dict):
        return {k: _layer_data(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return Vt.DoubleArray([float(v) for v in value])
    return value


def coloured(asset: Asset, rgb) -> Asset:
    """The asset with every material's base colour set to `rgb` (linear)."""
    rgb = tuple(float(c) for c in rgb)
    return replace(asset, materials=tuple(replace(m, base_color=rgb) for m in asset.materials))


def load_hazard(path: Path, name: str, units: str | None, up_axis: str | None) -> tuple[Asset, dict]:
    """(Asset in metres, Z up, centred on its bounding box; what the conversion used), or a PlanError
    (also for a size outside SIZE_M or more than MAX_TRIANGLES faces)."""
    asset, info = import_model(path, name, units, up_axis)
    n = sum(int(p.face_counts.size) for p in asset.parts)
    if n > MAX_TRIANGLES:
        raise PlanError(f"anomaly {name!r}: {path} has {n:,} faces, above the {MAX_TRIANGLES:,} a hazard may have; "
                        "fix: decimate it")
    extent = check_size(asset, path, name, info["unit"])
    info["extentM"] = [round(float(e), 6) for e in extent]
    return asset, info


def check_size(asset: Asset, path: Path, name: str, unit: str, what: str = "anomaly", size_m=SIZE_M,
               kind: str = "a hazard near the station", give: str = 'units = "mm", "cm", "in", ...',
               read_as: str = "") -> np.ndarray:
    """The asset's bounding-box extent (metres), or a PlanError naming the unit it was read with when its
    longest side is outside `size_m`: almost always a unit mistake. The one size check of a plan's
    hazards (load_hazard) and of `allo-usd asset import` (which gives `kind`, `give` as its options and
    `read_as`, how a unit it did not get was chosen)."""
    lo, hi = asset.bounds()
    extent = hi - lo
    if not (np.isfinite(extent).all() and size_m[0] <= extent.max() <= size_m[1]):
        raise PlanError(f"{what} {name!r}: {path} measures {extent.max():.4g} m along its longest side with units "
                        f"{unit!r}{read_as}, outside the {size_m[0]:g}-{size_m[1]:g} m {kind} may measure; fix: give "
                        f"the unit the file is in ({give})")
    return extent


def import_model(path: Path, name: str | None, units: str | None, up_axis: str | None,
                 what: str = "anomaly") -> tuple[Asset, dict]:
    """Any model file the project reads, as an Asset in metres, Z up, centred on its bounding box: a
    mesh file through allo_usd.assets.importer (units/up_axis None or 'auto': the format's rule), a USD
    file with pxr (`read_usd_hazard`). The one importer of `allo-usd asset import` and of a plan's
    hazards. Returns (asset, {format, unit, unitScale, upAxis, triangles, droppedTriangles}); errors
    are PlanErrors beginning with `what` and the name (e.g. "anomaly 'bracket': ...")."""
    path = Path(path)
    if path.suffix.lower() in HAZARD_USD_SUFFIXES:
        return read_usd_hazard(path, name or _NAME.sub("_", path.stem.split(".")[0]) or "model",
                               None if units == "auto" else units, None if up_axis == "auto" else up_axis, what)
    else:
        from allo_usd.assets.importer import import_mesh_report

        try:
            report = import_mesh_report(path, units=units or "auto", up_axis=up_axis or "auto", name=name)
        except AlloError as exc:
            fix = "" if "fix" in str(exc) else "; fix: re-export the model from its tool (as glTF, OBJ, STL or USD)"
            raise PlanError(f"{what} {name or path.stem!r}: {exc}{fix}") from None
        except Exception as exc:   # trimesh's parsers raise anything on a broken file
            raise PlanError(f"{what} {name or path.stem!r}: {path} could not be read as a {path.suffix} model "
                            f"({type(exc).__name__}: {str(exc)[:200]}); fix: re-export it") from None
        asset = replace(report.asset, name=name) if name else report.asset
        info = {"format": report.format, "unit": report.unit, "unitScale": report.scale, "upAxis": report.source_up_axis,
                "triangles": int(report.triangles), "droppedTriangles": int(report.dropped_triangles)}
        return asset, info


_NAME = re.compile(r"[^A-Za-z0-9_]")


def read_usd_hazard(path: Path, name: str, units: str | None, up_axis: str | None,
                    what: str = "anomaly") -> tuple[Asset, dict]:
    """A USD file's meshes as an Asset (see the module doc): world transforms, metersPerUnit and upAxis
    from the file (or the plan, which must then agree), one part per mesh with its bound constant
    material. Textures are not carried over. Every file the stage reads is checked before USD
    opens it (usd_hazard_walk); the stage must compose without errors, and every layer it used must
    be one the walk checked."""
    from pxr import Tf, Usd, UsdGeom

    from allo_usd.assets.importer import UP_AXIS_ROTATIONS, kept_triangles
    from allo_usd.assets.mesh import fan_triangulate
    from allo_usd.core.errors import LayerError
    from allo_usd.usd.dependencies import tf_message
    from allo_usd.usd.reader_bounds import mesh_topology, object_meshes, world_matrix

    def fail(why: str) -> PlanError:
        return PlanError(f"{what} {name!r}: {path} {why}")

    walked = usd_hazard_walk(path, name, what)   # its Sdf layers stay open for the stage: each is parsed once
    try:
        stage = Usd.Stage.Open(str(path), Usd.Stage.LoadAll)
    except Tf.ErrorException as exc:
        raise fail(f"is not a readable USD file ({tf_message(exc)[:200]}); fix: re-export it") from None
    if stage is None:
        raise fail("could not be opened as a USD stage; fix: re-export it")
    _check_composed(stage, walked, fail)
    composes = composed_layers(walked, path)
    del walked
    scale, unit = _usd_units(stage, units, fail)
    up = _usd_up_axis(stage, up_axis, fail)
    rot = UP_AXIS_ROTATIONS[up]
    cache = UsdGeom.XformCache(Usd.TimeCode.Default())
    parts, materials, seen, n_in = [], {}, set(), 0
    # Instanced meshes count (instance proxies); guide and proxy purposes are not the object itself.
    for prim in object_meshes(stage.GetPseudoRoot(),
                              lambda limit: fail(f"holds more than {limit:,} prims; fix: give a single hazard model")):
        try:
            points, counts, indices = mesh_topology(prim)
            m = world_matrix(cache, prim)
        except LayerError as exc:
            raise fail(f"has a mesh this importer refuses: {exc}") from None
        tris = fan_triangulate(counts, indices)
        n_in += len(tris)
        pts = fm.apply(rot, (fm.apply(m[:3, :3], points.astype(np.float64)) + m[:3, 3]) * scale)
        keep = kept_triangles(pts, tris)   # the importer's rule: zero-area ones are dropped, and counted
        if not keep.all():   # then unused points go, as the importer's (a mesh without drops keeps its points)
            used, inverse = np.unique(tris[keep], return_inverse=True)
            pts, tris = pts[used], inverse.reshape(-1, 3)
        if not len(tris):
            continue
        mat = _usd_material(prim, materials)
        base = _NAME.sub("_", prim.GetName()) or "mesh"
        part_name, k = base, 2
        while part_name in seen:
            part_name, k = f"{base}_{k}", k + 1
        seen.add(part_name)
        parts.append(MeshPart(part_name, pts, np.full(len(tris), 3, dtype=np.int32), tris.reshape(-1), mat.name))
    if not parts:
        raise fail("holds no visible mesh with faces; fix: export the hazard's geometry as UsdGeom.Mesh prims")
    lo = np.min([p.points.min(axis=0) for p in parts], axis=0)
    hi = np.max([p.points.max(axis=0) for p in parts], axis=0)
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
        raise fail("has points that are not finite; fix: re-export it")
    centre = (lo + hi) / 2
    parts = [replace(p, points=p.points - centre) for p in parts]
    asset = Asset(name, tuple(parts), tuple(materials.values()))
    kept = int(sum(p.face_counts.size for p in parts))
    info = {"format": "usd", "unit": unit, "unitScale": scale, "upAxis": up,
            "triangles": kept, "droppedTriangles": n_in - kept}
    if composes:   # every other layer it was made from (a single-file hazard's record is as before)
        info["composes"] = composes
    return asset, info


def _check_composed(stage, walked, fail) -> None:
    """The stage composed without errors and read no layer the walk did not check (a second line
    of defence behind usd_hazard_walk)."""
    import os

    from allo_usd.usd.safety import in_package

    errors = stage.GetCompositionErrors()
    if errors:
        try:
            first = " ".join(str(errors[0]).split())[:300]
        except UnicodeDecodeError:
            first = "an error whose text is not UTF-8"
        raise fail(f"does not compose ({len(errors)} composition error(s), the first: {first}); fix: restore the "
                   "files it names or correct their paths")
    checked = set(walked.layer_files())
    package = walked.files[0] if walked.files and walked.files[0].lower().endswith(".usdz") else None
    for layer in stage.GetUsedLayers():
        real = layer.realPath
        if layer.anonymous or not real:
            continue
        if not (in_package(real, package) if package else os.path.realpath(real) in checked):
            raise fail(f"read {real}, a layer the hazard's check did not pass; fix: keep every file the hazard "
                       "uses beside it and name them by relative paths")


def _usd_units(stage, units: str | None, fail) -> tuple[float, str]:
    from pxr import UsdGeom

    from allo_usd.assets.importer import UNIT_SCALES

    authored = stage.HasAuthoredMetadata("metersPerUnit")
    mpu = float(UsdGeom.GetStageMetersPerUnit(stage))
    if units is None:
        if not authored:
            raise fail("declares no metersPerUnit (USD then assumes centimetres); fix: give units in the plan")
        if not (math.isfinite(mpu) and mpu > 0):
            raise fail(f"declares metersPerUnit = {mpu}; fix: correct the file or give units")
        named = [u for u, s in UNIT_SCALES.items() if math.isclose(s, mpu, rel_tol=1e-9)]
        return mpu, named[0] if named else f"{mpu:g} m"
    if authored and not math.isclose(UNIT_SCALES[units], mpu, rel_tol=1e-9):
        raise fail(f"declares metersPerUnit = {mpu:g}, but the plan says units = {units!r} "
                   f"({UNIT_SCALES[units]:g} m); fix: leave units out (the file's is used) or correct one of them")
    return UNIT_SCALES[units], units


def _usd_up_axis(stage, up_axis: str | None, fail) -> str:
    from pxr import UsdGeom

    authored = stage.HasAuthoredMetadata("upAxis")
    file_up = str(UsdGeom.GetStageUpAxis(stage)).lower()
    if up_axis is None:
        if not authored:
            raise fail("declares no upAxis (USD then assumes Y); fix: give up_axis in the plan")
        return file_up
    if authored and up_axis != file_up:
        raise fail(f"declares upAxis = {file_up.upper()}, but the plan says up_axis = {up_axis!r}; fix: leave up_axis "
                   "out (the file's is used) or correct one of them")
    return up_axis


def _usd_material(prim, materials: dict) -> Material:
    """The mesh's bound UsdPreviewSurface (constant inputs) or its displayColor, as a Material."""
    from pxr import UsdGeom, UsdShade

    from allo_usd.assets.importer import DEFAULT_MATERIAL

    bound = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()[0]
    if bound:
        key = str(bound.GetPath())
        if key not in materials:
            colour, metallic, roughness = DEFAULT_MATERIAL.base_color, 0.0, 0.5
            shader = bound.ComputeSurfaceSource()[0]
            if shader:
                colour = _input(shader, "diffuseColor", colour, 3)
                metallic = _input(shader, "metallic", metallic, 1)
                roughness = _input(shader, "roughness", roughness, 1)
            materials[key] = Material(f"material_{len(materials) + 1}", colour, metallic, roughness)
        return materials[key]
    primvar = UsdGeom.PrimvarsAPI(prim).GetPrimvar("displayColor")
    value = primvar.Get() if primvar and primvar.HasAuthoredValue() else None
    colour = _clip(value[0], DEFAULT_MATERIAL.base_color, 3) if value is not None and len(value) else None
    key = f"displayColor:{colour}"
    if key not in materials:
        materials[key] = (Material(f"material_{len(materials) + 1}", colour, 0.0, 0.5) if colour is not None
                          else replace(DEFAULT_MATERIAL, name=f"material_{len(materials) + 1}"))
    return materials[key]


def _input(shader, name: str, default, n: int):
    inp = shader.GetInput(name)
    value = inp.Get() if inp and not inp.HasConnectedSource() else None
    return default if value is None else _clip(value, default, n)


def _clip(value, default, n: int):
    """A finite colour (n=3) or factor (n=1) clipped to 0..1, else the default."""
    v = np.asarray(value, dtype=np.float64).reshape(-1)
    if v.size != n or not np.isfinite(v).all():
        return default
    v = np.clip(v, 0.0, 1.0)
    return tuple(float(c) for c in v) if n == 3 else float(v[0])


def hazard_provenance(layer) -> dict | None:
    """The conversion record a hazard interface layer (an Sdf.Layer) carries, if it is one."""
    data = dict(layer.customLayerData or {})
    hazard = dict(data.get("allo", {})).get("hazard") if isinstance(data.get("allo"), dict) else None
    return dict(hazard) if isinstance(hazard, dict) and hazard else None
