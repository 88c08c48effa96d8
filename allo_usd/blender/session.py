"""A warm render session: one Blender scene kept across renders, patched from scene to scene.

`Session.render(desc)` builds the first description from scratch (`build.build_scene`); every
later one is diffed against the description the scene now shows, and only what differs is
applied:
- camera, body and anomaly matrices, pass indices, ray visibility, material assignment (every
  matrix through `build.place`: a quaternion rotation mode, never Euler angles);
- the sun lamps (the station's and each body's: direction, irradiance, angle, colour patched in
  place; a lamp that goes off is removed with its receiver collection, and one whose light
  linking or linked meshes changed is rebuilt);
- the inspection spot light (on/off, transform, power, cone);
- the other lamps (SceneDescription.lights: sphere, rect, disk, cylinder lights) and the dome are
  kept while they are the same (the dome set again after configure_render); when any of them
  differs the scene is built from scratch (`_lamps_differ`);
- render settings (resolution, samples, seed, exposure, threads, denoise, ...) and the render
  device (allo_usd.blender.device: not in the description, passed to `render`/`apply`);
- the compositor (glare on/off);
- materials whose values changed (patched in place, or rebuilt when the node graph differs);
- meshes that came, went or changed geometry (the anomaly in/out or changing asset/variant):
  the old objects, their meshes and materials are removed and orphan data purged
  (`bpy.data.orphans_purge(do_recursive=True)`) before the new ones are built.

A mesh is kept when its prim path and geometry (points, face counts and indices, UVs, smooth
flag) are unchanged; geometry is compared by a digest computed once per MeshDesc. When less
than half of the description's points could be kept (another base stage), the session builds
from scratch.

Byte-identical to a fresh build (tests/blender/test_session.py, and 10/10 scenes on the real stage in
scripts/bench_session.py): Cycles with the same seed renders the same scene to the same bytes.
What makes the patched scene "the same scene":
- every value is set through the same builder code a fresh build uses (build.build_* and
  build.configure_render); a spot light is simply rebuilt when anything about it changes, and a
  material is rebuilt unless only its plain Principled values differ;
- names are freed before they are taken again (old objects, meshes and materials removed and
  orphans purged first), so new datablocks get exactly the fresh build's names, never `.001`;
- objects are linked in the fresh build's order (meshes in description order, camera, suns,
  spot): the depsgraph, and so Cycles' object and light lists, follow the scene collection's
  order. In the tests the bytes matched even without this step (Cycles' per-object random
  numbers hash the name, not the index), but it costs only an unlink/link of the tail, no
  geometry work, so it is kept as a guarantee;
- the world is reused (build.configure_render no longer creates a `Space.001` per call).
Persistent data (`use_persistent_data`, set by configure_render for both paths) lets Cycles keep
unchanged geometry between renders. Switch cost and warm vs cold scenes: docs/benchmarks/bench_session.md
(the station is small, so the render dominates either way).

A Session must own the process's Blender scene: a fresh build elsewhere (render_scene, a file
load) replaces it, which the session notices (a token on the scene, live object pointers) and
answers with a full build.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass, field, fields
from pathlib import Path

import numpy as np

from allo_usd.usd.description import MaterialDesc, MeshDesc, SceneDescription
from allo_usd.blender import build
from allo_usd.blender.render import RenderResult, render_current

_TOKEN = "allo_session"


def geometry_digest(mesh: MeshDesc) -> bytes:
    """Digest of what a Blender mesh datablock is built from (not the matrix, material or class)."""
    h = hashlib.blake2b(digest_size=16)
    for arr in (mesh.points, mesh.face_counts, mesh.face_indices):
        a = np.ascontiguousarray(arr)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.data)
    if mesh.uv is None:
        h.update(b"no-uv")
    else:
        a = np.ascontiguousarray(mesh.uv)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.data)
    h.update(b"smooth" if mesh.smooth else b"flat")
    for _, faces in mesh.subsets:   # the faces of each material slot (a mesh without subsets digests as before)
        h.update(b"subset" + np.ascontiguousarray(faces, dtype=np.int32).tobytes())
    if mesh.colors is not None:   # a mesh without display colours digests as before
        a = np.ascontiguousarray(mesh.colors)
        h.update(b"colors" + str((a.dtype.str, a.shape)).encode())
        h.update(a.data)
    return h.digest()


@dataclass
class ApplyStats:
    """What the last `Session.apply` did."""
    full_build: bool = False
    seconds: float = 0.0
    meshes_kept: int = 0
    meshes_added: list[str] = field(default_factory=list)
    meshes_removed: list[str] = field(default_factory=list)
    materials_patched: list[str] = field(default_factory=list)
    materials_rebuilt: list[str] = field(default_factory=list)
    changed: list[str] = field(default_factory=list)   # camera, sun, spot, render, compositor, ...
    reordered: bool = False
    purged: int = 0


def _eq(a, b) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return np.array_equal(np.asarray(a), np.asarray(b))
    return a == b


def _same(a, b) -> bool:
    """Two descriptions (dataclasses holding arrays) equal field by field; None only equals None."""
    if a is None or b is None:
        return a is b
    return type(a) is type(b) and all(_eq(getattr(a, f.name), getattr(b, f.name)) for f in fields(a))


class Session:
    """One Blender scene kept warm across renders in this process (bpy has one global state:
    use one Session per process)."""

    def __init__(self, min_kept_fraction: float = 0.5):
        self.desc: SceneDescription | None = None
        self.min_kept_fraction = min_kept_fraction
        self.full_builds = 0
        self.applies = 0
        self.last = ApplyStats()
        self._digests: dict[str, tuple[MeshDesc, bytes]] = {}   # path -> (desc it was computed for, digest)
        self._objects: dict[str, object] = {}                   # mesh prim path -> Blender object
        self._materials: dict[str, object] = {}                 # material key -> Blender material
        self._token = f"{id(self):x}-{time.monotonic_ns():x}"
        self.device = None   # the allo_usd.blender.device.Device the scene renders on (None: the CPU)

    # ---------------------------------------------------------------- public

    def render(self, desc: SceneDescription, workdir: Path | None = None, device=None) -> RenderResult:
        self.apply(desc, device)
        try:
            return render_current(desc, workdir)
        except BaseException:
            self.invalidate()
            raise

    def apply(self, desc: SceneDescription, device=None) -> ApplyStats:
        """Make the Blender scene show `desc`, rendering on `device` (an allo_usd.blender.device.Device;
        None: the CPU); returns what was done (also in `self.last`)."""
        t0 = time.perf_counter()
        try:
            if self.desc is None or not self._alive() or not self._patchable(desc) or self._lamps_differ(desc):
                stats = self._full_build(desc, device)
            else:
                stats = self._patch(desc, device)
                build.set_object_ids(desc)  # ids follow the set of mesh paths (build.object_ids)
        except BaseException:
            self.invalidate()
            raise
        self.desc, self.device = desc, device
        current = {m.path for m in desc.meshes}
        self._digests = {p: v for p, v in self._digests.items() if p in current}  # hold no old arrays
        stats.seconds = time.perf_counter() - t0
        self.last = stats
        self.applies += 1
        return stats

    def _lamps_differ(self, desc: SceneDescription) -> bool:
        """The other lamps or the dome differ: patched in place (or a lamp rebuilt while the world changes),
        Cycles' light list can come out in another order than a fresh build's, and the noise with it
        (measured: 4 % of the pixels), so the scene is built from scratch. A sequence of scenes under
        one user layer keeps its lamps, and pays nothing."""
        prev = self.desc
        return len(prev.lights) != len(desc.lights) or not all(_same(a, b) for a, b in zip(prev.lights, desc.lights)) \
            or not _same(prev.dome, desc.dome) \
            or any(x.link is not None for x in desc.lights)  # linked to meshes that may be rebuilt

    def _alive(self) -> bool:
        """The Blender scene is still the one this session built (a fresh build or a file load elsewhere
        in the process, e.g. render_scene, replaces it and frees every object the session holds)."""
        import bpy

        try:
            return bpy.context.scene.get(_TOKEN) == self._token and all(o.name for o in self._objects.values())
        except ReferenceError:
            return False

    def invalidate(self) -> None:
        """Forget the current scene: the next render builds from scratch."""
        self.desc = None
        self._objects.clear()
        self._materials.clear()

    # ---------------------------------------------------------------- digests

    def _digest(self, mesh: MeshDesc) -> bytes:
        cached = self._digests.get(mesh.path)
        if cached is not None and cached[0] is mesh:
            return cached[1]
        d = geometry_digest(mesh)
        self._digests[mesh.path] = (mesh, d)
        return d

    def _patchable(self, desc: SceneDescription) -> bool:
        self._old_digests = {p: d for p, (_, d) in self._digests.items()}
        old = {m.path: self._old_digests.get(m.path) for m in self.desc.meshes}
        self._kept = set()
        kept_points = total_points = 0
        for m in desc.meshes:
            total_points += len(m.points)
            if m.path in old and old[m.path] is not None and self._digest(m) == old[m.path]:
                self._kept.add(m.path)
                kept_points += len(m.points)
            else:
                self._digest(m)
        return bool(self._kept) and kept_points >= self.min_kept_fraction * total_points

    # ---------------------------------------------------------------- from scratch

    def _full_build(self, desc: SceneDescription, device) -> ApplyStats:
        import bpy

        build.build_scene(desc, device)
        self.full_builds += 1
        bpy.context.scene[_TOKEN] = self._token  # a custom property: Cycles never reads it
        objs = {o.name: o for o in bpy.context.scene.collection.objects}
        self._objects = {m.path: objs[m.path] for m in desc.meshes}
        self._materials = {k: bpy.data.materials[m.path] for k, m in desc.materials.items()}
        for m in desc.meshes:
            self._digest(m)
        return ApplyStats(full_build=True, meshes_added=[m.path for m in desc.meshes])

    # ---------------------------------------------------------------- incremental

    def _patch(self, desc: SceneDescription, device) -> ApplyStats:
        stats = ApplyStats()
        prev = self.desc
        removed = [m.path for m in prev.meshes if m.path not in self._kept]
        added = [m for m in desc.meshes if m.path not in self._kept]
        patch_mats = self._remove_gone(prev, desc, removed, stats)
        self._build_materials(prev, desc, patch_mats, stats)
        self._build_meshes(prev, desc, added, stats)
        self._patch_view(prev, desc, added, stats)
        self._patch_output(prev, desc, device, stats)
        stats.reordered = self._reorder(desc)
        return stats

    def _remove_gone(self, prev: SceneDescription, desc: SceneDescription, removed: list[str],
                     stats: ApplyStats) -> list[str]:
        """Step 1: remove meshes that go and materials that are gone or must be rebuilt, then purge,
        so nothing stale stays behind; returns the materials to patch in place."""
        import bpy

        for path in removed:
            obj = self._objects.pop(path)
            data = obj.data
            bpy.data.objects.remove(obj, do_unlink=True)
            if data is not None and data.users == 0:
                bpy.data.meshes.remove(data)
        stats.meshes_removed = removed
        rebuild_mats, patch_mats = [], []
        for key, mat in list(self._materials.items()):
            new = desc.materials.get(key)
            old = prev.materials.get(key)
            if new is None or new.path != old.path:
                rebuild_mats.append(key) if new is not None else None
                self._drop_material(key)
            elif new != old:
                if self._can_patch_material(old, new):
                    patch_mats.append(key)
                else:
                    rebuild_mats.append(key)
                    self._drop_material(key)
        if removed or rebuild_mats or any(k not in desc.materials for k in prev.materials):
            stats.purged = self._purge()
            for key, mat in list(self._materials.items()):  # a material whose only mesh went was purged too
                try:
                    mat.name
                except ReferenceError:
                    del self._materials[key]
        return patch_mats

    def _build_materials(self, prev: SceneDescription, desc: SceneDescription, patch_mats: list[str],
                         stats: ApplyStats) -> None:
        """Step 2: build the new and rebuilt materials in description order (as a fresh build does),
        patch the rest."""
        for key, m in desc.materials.items():
            if key not in self._materials:
                self._materials[key] = build.build_material(m)
                if key in prev.materials:
                    stats.materials_rebuilt.append(key)
        for key in patch_mats:
            self._patch_material(self._materials[key], desc.materials[key])
            stats.materials_patched.append(key)

    def _build_meshes(self, prev: SceneDescription, desc: SceneDescription, added: list[MeshDesc],
                      stats: ApplyStats) -> None:
        """Step 3: build the new meshes and patch the kept ones, in description order."""
        prev_by_path = {m.path: m for m in prev.meshes}
        for m in desc.meshes:
            if m.path in self._kept:
                self._patch_mesh(self._objects[m.path], prev_by_path[m.path], m)
            else:
                self._objects[m.path] = build.build_mesh(m, self._materials[m.material],
                                                         [self._materials[k] for k, _ in m.subsets])
        stats.meshes_added = [m.path for m in added]
        stats.meshes_kept = len(self._kept)

    def _patch_view(self, prev: SceneDescription, desc: SceneDescription, added: list[MeshDesc],
                    stats: ApplyStats) -> None:
        """Step 4: camera and lights, touched only where they differ (suns linked to rebuilt meshes too)."""
        pc, nc = prev.camera, desc.camera
        if not _eq(pc.matrix, nc.matrix) or _lens(pc) != _lens(nc):
            self._patch_camera(desc)
            stats.changed.append("camera")
        if self._patch_suns(prev, desc, {m.path for m in added}):
            stats.changed.append("sun")
        if not self._spot_equal(prev.spot, desc.spot):
            self._patch_spot(desc)
            stats.changed.append("spot")

    def _patch_output(self, prev: SceneDescription, desc: SceneDescription, device, stats: ApplyStats) -> None:
        """Step 5: render settings, device and compositor, reconfigured only when they differ."""
        if prev.render != desc.render or prev.effects.body_shine != desc.effects.body_shine:
            build.configure_render(desc.render, device)
            if desc.dome is not None:
                build.set_dome(desc.dome)  # configure_render turns the world black
            stats.changed.append("render")
        elif device != self.device:
            from allo_usd.blender.device import activate

            activate(device)
            stats.changed.append("device")
        if prev.effects.glare != desc.effects.glare:
            from allo_usd.blender.compositor import build_glare, no_compositor

            if desc.effects.glare:
                build_glare()
            else:
                no_compositor()
                stats.purged += self._purge()
            stats.changed.append("compositor")

    def _drop_material(self, key: str) -> None:
        import bpy

        mat = self._materials.pop(key)
        bpy.data.materials.remove(mat, do_unlink=True)

    @staticmethod
    def _purge() -> int:
        import bpy

        n = bpy.data.orphans_purge(do_local_ids=True, do_linked_ids=True, do_recursive=True)
        return int(n or 0)

    @staticmethod
    def _can_patch_material(old: MaterialDesc, new: MaterialDesc) -> bool:
        """Only the Principled BSDF's plain values differ, and the node graph is the same."""
        if old.base_color_texture or new.base_color_texture:
            return False
        return old.emissive_color == new.emissive_color

    @staticmethod
    def _patch_material(mat, desc: MaterialDesc) -> None:
        build.set_principled(next(n for n in mat.node_tree.nodes if n.type == "BSDF_PRINCIPLED"), desc)

    def _patch_mesh(self, obj, old: MeshDesc, new: MeshDesc) -> None:
        if not _eq(old.matrix, new.matrix):
            build.place(obj, new.matrix)
        if old.ray_visibility != new.ray_visibility:
            for attr in ("visible_camera", "visible_diffuse", "visible_glossy", "visible_shadow",
                         "visible_transmission", "visible_volume_scatter"):
                setattr(obj, attr, True)
            if new.ray_visibility == "cameraOnly":
                obj.visible_diffuse = obj.visible_glossy = obj.visible_shadow = False
                obj.visible_transmission = obj.visible_volume_scatter = False
            elif new.ray_visibility == "noShadow":
                obj.visible_shadow = False
        for slot, key in enumerate((new.material, *(k for k, _ in new.subsets))):   # as many slots: same digest
            mat = self._materials[key]
            if obj.data.materials[slot] != mat:
                obj.data.materials[slot] = mat

    @staticmethod
    def _find(name: str):
        import bpy

        for o in bpy.context.scene.collection.objects:
            if o.name == name:
                return o
        return None

    def _patch_camera(self, desc: SceneDescription) -> None:
        obj = self._find(self.desc.camera.path)  # the camera the scene shows now
        if obj.name != desc.camera.path:   # the render settings name another camera prim: named as built
            obj.name = obj.data.name = desc.camera.path
        build.set_lens(obj.data, desc.camera)
        build.place(obj, desc.camera.matrix)

    def _remove_light(self, name: str) -> None:
        """Remove a light object, its data and its light-linking collections."""
        import bpy

        obj = self._find(name)
        if obj is not None:
            data = obj.data
            colls = [c for c in (obj.light_linking.receiver_collection, obj.light_linking.blocker_collection) if c]
            bpy.data.objects.remove(obj, do_unlink=True)
            if data is not None and data.users == 0:
                bpy.data.lights.remove(data)
            for coll in colls:
                if coll.users == 0:
                    bpy.data.collections.remove(coll)

    def _patch_suns(self, prev: SceneDescription, desc: SceneDescription, rebuilt_meshes: set[str]) -> bool:
        """Sun lamps: remove those now off, patch values in place, rebuild a lamp whose light linking
        changed or names a mesh object that was rebuilt (removing an object drops it from collections)."""
        old = {s.path: s for s in prev.suns}
        new = {s.path: s for s in desc.suns}
        changed = False
        for path in old:
            if path not in new:
                self._remove_light(path)
                changed = True
        for path, s in new.items():
            obj = self._find(path)
            before = old.get(path)
            if obj is None or before is None or before.link != s.link or (
                    s.link is not None and not rebuilt_meshes.isdisjoint(s.link.paths)):
                self._remove_light(path)
                build.build_sun(s)
                changed = True
            elif before != s:
                build.set_sun(obj, s)
                changed = True
        return changed

    @staticmethod
    def _spot_equal(a, b) -> bool:
        if a is None or b is None:
            return a is b
        return (_eq(a.matrix, b.matrix) and (a.path, a.radius, a.intensity, a.color, a.cone_angle_deg, a.softness)
                == (b.path, b.radius, b.intensity, b.color, b.cone_angle_deg, b.softness))

    def _patch_spot(self, desc: SceneDescription) -> None:
        # A spot is cheap to build: remove and build it again, so every value is set as a fresh build sets it.
        for spot in (self.desc.spot, desc.spot):  # the one the scene shows now (and its name for the new one)
            if spot is not None:
                self._remove_light(spot.path)
        if desc.spot is not None:
            build.build_spot(desc.spot)

    def _reorder(self, desc: SceneDescription) -> bool:
        """Step 6: link objects in the order a fresh build does (meshes, camera, suns, spot, other lamps)."""
        import bpy

        coll = bpy.context.scene.collection
        want = [self._objects[m.path] for m in desc.meshes] + [self._find(desc.camera.path)]
        for name in tuple(s.path for s in desc.suns) + ((desc.spot.path,) if desc.spot is not None else ()) \
                + tuple(build.lamp_name(x) for x in desc.lights):
            want.append(self._find(name))
        have = list(coll.objects)
        if have == want:
            return False
        i = 0
        while i < min(len(have), len(want)) and have[i] == want[i]:
            i += 1
        for o in have[i:]:
            coll.objects.unlink(o)
        for o in want[i:]:
            coll.objects.link(o)
        return True


def _lens(cam) -> tuple:
    """Everything of a CameraDesc but its matrix: what set_lens and the object's name take."""
    return (cam.path, cam.focal_length_mm, cam.sensor_width_mm, cam.sensor_height_mm, cam.clip,
            cam.horizontal_offset_mm, cam.vertical_offset_mm, cam.f_stop, cam.focus_distance_m)
