"""One render job: a scene layer in, its files out (PNG, EXR, mask, metadata).

The unit of work for local pools and Dask alike. Outputs are written atomically and the
metadata JSON goes last, so its presence (naming the render's identity: the checksums of every
file the composition read, and the versions that affect pixels) marks a finished scene and
re-runs skip it while that identity holds (allo_usd.run.render_index.is_done). The JSON is a
RenderRecord (allo_usd.output.record; its fields: docs/render_record.md).

The JSON also records what rendered (`device`: the device asked for and used, the GPU backend and
names or the CPU model, and Blender's version and build, allo_usd.blender.device.record). The
device is not part of the identity: it changes noise, not meaning (docs/guide/dispatch.md, "GPU rendering").
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from allo_usd.core.version import __version__
from allo_usd.core.interrupts import import_held
from allo_usd.core.provenance import library_versions
from allo_usd.output.annotations import image_annotations
from allo_usd.output.checksums import file_sha256
from allo_usd.output.identity import (done_record, input_hashes, outputs_sha256, render_identity, render_target,
                                      render_versions)
from allo_usd.output.record import RenderRecord
from allo_usd.output.render_outputs import check_output_names, output_paths
from allo_usd.output.writers import write_exr, write_instance_png, write_mask_png, write_rgb_exr, write_rgb_png
from allo_usd.core.files import relpath
from allo_usd.run.options import JobOptions
from allo_usd.run.render_index import MANIFEST, append_jsonl, index_row
from allo_usd.usd.sniff import layer_outputs


def apply_effects(desc, rgb: np.ndarray) -> tuple[np.ndarray, dict]:
    """Post-render effects the layer declares, on linear data; each absent effect costs nothing."""
    applied = {}
    if desc.effects.sensor_noise:
        from allo_usd.core.sensor import SensorParams
        from allo_usd.output.sensor_noise import apply_sensor_noise

        # The layer's sensor (allo:effects:sensor:*): its seed fixes PRNU/DSNU, the render seed
        # draws the temporal noise. The JSON repeats the resolved parameters; the layer is the record.
        params = (desc.effects.sensor or SensorParams()).resolved(desc.render.exposure)
        rgb = apply_sensor_noise(rgb, desc.render.exposure, seed=desc.render.seed, params=params)
        record = params.as_dict()
        record["sensor_seed"] = record.pop("seed")
        applied["sensor_noise"] = {"model": "EMVA 1288", "temporal_seed": desc.render.seed, **record}
    return rgb, applied


def object_pixels(ids: np.ndarray, objects: tuple[str, ...]) -> dict:
    """The JSON's "station_fraction" (station pixels / all pixels) and "bodies" ({"sun": {"pixels": n},
    ...}: visible pixels of each body), from the object id image and the prim path of each id."""
    from allo_usd.usd.layout import STATION, body_path

    counts = np.bincount(ids.ravel(), minlength=len(objects) + 1)

    def under(root: str) -> int:
        return int(sum(counts[i] for i, p in enumerate(objects, start=1) if p == root or p.startswith(root + "/")))

    return {"station_fraction": under(STATION) / ids.size,
            "bodies": {b.lower(): {"pixels": under(body_path(b))} for b in ("Sun", "Earth", "Moon")}}


def aimed_target(settings, options: JobOptions) -> tuple[float, float]:
    """(target_psnr, time_limit) of render settings that carry them (a RenderDesc, a plan's Quality) with
    the run's (JobOptions.target_psnr, time_limit; None keeps the settings' own), the pair checked as a
    plan's is, in one line naming the options."""
    from allo_usd.core.errors import AlloError
    from allo_usd.plan.settings import target_problem

    target = settings.target_psnr if options.target_psnr is None else float(options.target_psnr)
    limit = settings.time_limit if options.time_limit is None else float(options.time_limit)
    if target == 0 and options.time_limit is None:
        limit = 0.0   # --target-psnr 0 renders fixed samples: the settings' time limit has nothing to stop
    problem = target_problem(target, limit, "--target-psnr", "--time-limit")
    if problem:
        raise AlloError(problem)
    return target, limit


def render_layer(layer: Path, out_dir: Path, force: bool = False, threads: int | None = None,
                 workdir: Path | None = None, session=None, save_blend: Path | None = None,
                 device: str = "auto", passes: tuple[str, ...] | None = None, index: bool = True,
                 target_psnr: float | None = None, time_limit: float | None = None, estimate: bool = False) -> dict:
    """Render one layer into out_dir; returns its metadata (also written as JSON): render_record's
    record as the JSON's object, for callers outside the package (allo_usd.render_layer). `force`,
    `threads`, `device`, `passes`, `save_blend`, `target_psnr`, `time_limit` and `estimate` build the JobOptions (allo_usd.run.options) that
    render_record reads; `workdir`, `session` and `index` are render_record's."""
    job = JobOptions(device=device, threads=threads, passes=passes, force=force, save_blend=save_blend,
                     target_psnr=target_psnr, time_limit=time_limit, estimate=estimate)
    return render_record(layer, out_dir, job, workdir=workdir, session=session, index=index).as_dict()


def render_record(layer: Path, out_dir: Path, options: JobOptions | None = None, *, workdir: Path | None = None,
                  session=None, index: bool = True) -> RenderRecord:
    """Render one layer into out_dir as `options` says (a JobOptions; None: its defaults); returns its
    record (a RenderRecord, also written as NAME.json).

    `options.threads` overrides the layer's allo:render:threads for this process only (the layer is
    not edited): a pool of N workers on C cores runs each with C // N threads. Cycles gives the same
    image for any thread count. `workdir` holds Blender's temporary render file. `session` (an
    allo_usd.blender.session.Session) keeps the Blender scene warm and applies only what differs
    from its previous scene; the files are byte-identical to a from-scratch build. `options.save_blend`
    also saves the built Blender scene there as a .blend (before rendering), to open what Blender got:
    checked before anything else (allo_usd.blender.debug.check_blend_target: an existing file is
    replaced only with `options.force`; a link, a directory, a device or another extension never) and
    written atomically.
    `options.device` is 'auto' (also for None), 'cpu' or 'gpu' (allo_usd.blender.device.select:
    probed once per process; 'gpu' without a GPU is a DeviceError before the layer is read).
    `options.passes` (allo_usd.plan.settings.PASSES) replaces the passes the layer orders for this run:
    the JSON records both ("passes" written, "layer_passes"), and a render with other passes than its
    layer's is never skipped as done.
    `options.target_psnr` / `time_limit` replace the layer's target mode for this run (aimed_target): the
    JSON records the target used ("target", in the identity) and the layer's ("layer_target"), and a
    render given either is never skipped as done.
    A scene is skipped (its JSON returned) when done by the rule every entry point shares
    (allo_usd.output.identity.done_record: the JSON beside the outputs is the record), whoever rendered
    it, unless `options.force`. A render into a folder that holds a dispatcher's manifest.jsonl appends
    the scene's row there (`index`; the dispatcher's workers pass False: their parent writes the row),
    so the index never names outputs that a later render replaced.
    """
    import dataclasses

    from allo_usd.usd.dependencies import walk
    from allo_usd.usd.read import read_scene

    from allo_usd.blender.device import cycles_cpu, record, select

    options = JobOptions() if options is None else options   # checked as it was built (device, passes)
    force, threads, save_blend, passes = options.force, options.threads, options.save_blend, options.passes
    check_output_names([layer])
    if save_blend is not None:
        from allo_usd.blender.debug import check_blend_target

        save_blend = check_blend_target(save_blend, replace=force)
    if passes is not None and passes == layer_outputs(layer):
        passes = None  # what the layer orders anyway
    aimed = options.target_psnr is not None or options.time_limit is not None   # another target than the layer's
    if not force and save_blend is None and passes is None and not aimed:
        meta = done_record(layer, out_dir)  # the rule every entry point uses (allo_usd.run.render_index.is_done)
        if meta is not None and not (options.estimate and not isinstance(getattr(meta, "accuracy", None), dict)):
            return meta
    import_held("bpy")   # Blender's start-up swallows a Ctrl-C (and leaves numpy half-loaded): held until it is in
    used = select(options.device or "auto")
    read = walk(layer)  # checked before USD opens a file; kept open so read_scene parses no layer twice
    inputs = input_hashes(layer, read.files)  # before the read: an edit meanwhile re-renders next time
    desc = read_scene(layer)
    del read
    if threads is not None:
        desc = dataclasses.replace(desc, render=dataclasses.replace(desc.render, threads=int(threads)))
    layer_passes, layer_target = desc.render.outputs, render_target(desc.render)
    if passes is not None:
        desc = dataclasses.replace(desc, render=dataclasses.replace(desc.render, outputs=passes))
    if aimed:
        target_psnr, time_limit = aimed_target(desc.render, options)
        desc = dataclasses.replace(desc, render=dataclasses.replace(desc.render, target_psnr=target_psnr,
                                                                    time_limit=time_limit))
    if options.estimate:
        desc = dataclasses.replace(desc, render=dataclasses.replace(desc.render, estimate=True))
    target = render_target(desc.render)
    result = _render(desc, workdir, session, save_blend, used, replace_blend=force)
    paths = output_paths(layer, out_dir, desc.render.outputs)
    effects = {}
    if "rgb" in paths or "exr" in paths:
        rgb, effects = apply_effects(desc, result.rgb)
        if "rgb" in paths:
            write_rgb_png(paths["rgb"], rgb)
        if "exr" in paths:
            write_rgb_exr(paths["exr"], rgb)
    if "mask" in paths:
        write_mask_png(paths["mask"], result.mask)
    if "depth" in paths:
        write_exr(paths["depth"], {"Z": result.depth}, half=False)
    if "normal" in paths:
        write_exr(paths["normal"], {c: result.normal[..., i] for i, c in enumerate("XYZ")}, half=False)
    if "instance" in paths:
        write_instance_png(paths["instance"], result.ids)
    if "amodal" in paths:
        write_mask_png(paths["amodal"], result.amodal)
    counts = np.bincount(result.mask.ravel(), minlength=3)
    meta = RenderRecord(
        layer=str(Path(layer).resolve()),   # where it was rendered from (this machine's path)
        layer_relative=relpath(Path(layer), Path(out_dir)),  # from the render folder: moves with the tree
        layer_sha256=file_sha256(layer),
        identity=render_identity(inputs, target=target),
        inputs=inputs,
        versions=render_versions(),
        libraries=library_versions(),   # every library that computes values, and the lock (core.provenance)
        package_version=__version__,
        device=record(used),
        cycles_cpu=cycles_cpu(),   # the CPU kernel Cycles used and the CPU flags that pick it
        render_seconds=round(result.seconds, 3),
        amodal_seconds=round(result.amodal_seconds, 3) if "amodal" in paths else None,
        resolution=list(desc.render.resolution),
        class_pixels={"background": int(counts[0]), "station_and_bodies": int(counts[1]), "anomaly": int(counts[2])},
        anomaly_fraction=float(counts[2] / result.mask.size),
        **object_pixels(result.ids, result.objects),
        passes=list(desc.render.outputs), layer_passes=list(layer_passes),
        target=target, layer_target=layer_target,   # both None for fixed samples: the JSON as before
        accuracy=result.accuracy,   # the render's own estimate of its error (None: not estimated)
        instances={str(i): p for i, p in enumerate(result.objects, start=1)} if "instance" in paths else None,
        scene=desc.meta,
        effects=effects,
        files={k: p.name for k, p in paths.items()},
        outputs_sha256=outputs_sha256(paths),  # what is_done checks: the JSON alone vouches for its outputs
        # K, pose, clipping, the anomaly's box and place, the bodies in view (conventions: output/annotations.py)
        annotations=image_annotations(desc, result.mask, result.amodal, result.ids),
    )
    meta.write(paths["meta"])
    if index and (Path(out_dir) / MANIFEST).is_file():  # a dispatcher's folder: its index follows the record
        append_jsonl(Path(out_dir) / MANIFEST, index_row(layer, out_dir, meta))
    return meta


def _render(desc, workdir: Path | None, session, save_blend: Path | None, device, replace_blend: bool = False):
    from allo_usd.blender.build import build_scene
    from allo_usd.blender.render import render_current

    if save_blend is None and session is not None:
        return session.render(desc, workdir, device)
    try:
        if session is None:
            build_scene(desc, device)
        else:
            session.apply(desc, device)
        if save_blend is not None:
            from allo_usd.blender.debug import save_blend as save

            save(save_blend, replace=replace_blend)
        return render_current(desc, workdir)
    except BaseException:
        if session is not None:
            session.invalidate()
        raise
