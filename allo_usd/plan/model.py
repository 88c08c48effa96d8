"""A dataset plan: what to make (days, poses, anomalies, counts, effects, quality, seeds), as a file.

A plan is a pydantic model stored as TOML or YAML (chosen by the file extension), so a dataset
is reproduced from one small, reviewable file. Validation happens when a plan is built or
loaded: every error names the field and the fix (`PlanError`). `enumerate_scenes` turns a plan
into the exact, deterministic list of scenes to author; nothing random is left to chance
outside the seeds the plan records. `paper_plan()` is the ALLO paper's Table II.
"""

from __future__ import annotations

import math
import reprlib
from datetime import date, datetime, time, timedelta, timezone
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_serializer, field_validator, model_validator

from allo_usd.assets.importer import SUPPORTED_EXTENSIONS, UNIT_SCALES, UP_AXIS_ROTATIONS
from allo_usd.core.camera_model import CLIP_M, DEFAULT_CAMERA, LENS_MM, SENSOR_MM, CameraModel, sensor_height_for
from allo_usd.core.errors import EpochError, PlanError
from allo_usd.core.limits import resolution_problem
from allo_usd.core.timefmt import format_utc, parse_utc
from allo_usd.plan.settings import (DEFAULT_PASSES, DENOISE_PREFILTERS, DENOISE_QUALITIES, DEVICES, PASSES, PRESETS,
                                    EffectFlags, QualitySettings, passes_problem, target_problem)

DEPTH_COUNT = 5  # allo_usd.scene.placement.DEPTH_OFFSETS: 0, -1, +1, -2, +2 m
N_POSES = 50
STATION_UNITS = ("auto", *UNIT_SCALES)
STATION_UP_AXES = ("auto", *UP_AXIS_ROTATIONS)
STATION_SUFFIXES = tuple(SUPPORTED_EXTENSIONS)   # what the importer reads (a USD station is not imported)
# A plan expands to at most this many scenes, and draws subsets from grids of at most this many
# (seed, day, pose) triples: counted arithmetically when the plan is validated, before anything is
# enumerated (the paper's plan has 51,409 scenes).
MAX_PLAN_SCENES = 10_000_000


_REPR = reprlib.Repr()
_REPR.maxstring = _REPR.maxother = _REPR.maxlong = 80
_REPR.maxlist = _REPR.maxtuple = _REPR.maxdict = _REPR.maxset = 6
_REPR.maxlevel = 3


def _short(value) -> str:
    """repr(value), cut to about 80 characters (a hostile plan's value can be megabytes)."""
    try:
        return _REPR.repr(value)
    except ValueError:   # an int past sys.get_int_max_str_digits()
        return f"<{type(value).__name__} too long to show>"


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class Dates(_Model):
    """Epochs at 00:00 UTC: `start`, `start + step_days`, ... (`days` of them), all inside DE421."""

    start: date = Field(date(2030, 1, 1), description="First epoch's date (00:00 UTC).")
    days: int = Field(365, ge=1, description="Number of epochs.")
    step_days: int = Field(1, ge=1, description="Days between consecutive epochs.")

    def epochs(self) -> list[datetime]:
        t0 = datetime(self.start.year, self.start.month, self.start.day, tzinfo=timezone.utc)
        return [t0 + timedelta(days=k * self.step_days) for k in range(self.days)]

    @model_validator(mode="after")
    def _inside_de421(self):
        # In whole days (ordinals), before any datetime is made: a last epoch past year 9999 or a
        # billion days is refused by arithmetic, not by an OverflowError or a billion datetimes.
        first_ok, last_ok = de421_dates()
        first = self.start.toordinal()
        last = first + (self.days - 1) * self.step_days
        if first < first_ok.toordinal() or last > last_ok.toordinal():
            past = last > date.max.toordinal()
            end = f"{self.start} + {last - first:,} days" if past else date.fromordinal(last).isoformat()
            raise ValueError(f"epochs {self.start} .. {end} (start + (days - 1) x step_days) leave the DE421 "
                             f"ephemeris, which covers {first_ok} .. {last_ok}; fix: choose dates.start, dates.days "
                             f"and dates.step_days so every epoch falls inside it")
        return self


def de421_dates() -> tuple[date, date]:
    """The first and last dates whose 00:00 UTC lies inside DE421 (allo_usd.sky.ephemeris_range)."""
    from allo_usd.sky.ephemeris_range import DE421_END_UTC, DE421_START_UTC

    lo, hi = (datetime.fromisoformat(s) for s in (DE421_START_UTC, DE421_END_UTC))
    first = lo.date() if lo.time() == time() else lo.date() + timedelta(days=1)
    return first, hi.date()


class Poses(_Model):
    """Base camera pose numbers (1..50) for training and for testing; the sets must not overlap.

    `file`: a pose file of the user's own poses (allo_usd.plan.posefile: CSV or JSON), relative to the
    working directory like station.source and base_stage. Its poses come in addition to the listed
    built-in ones (empty `train` and `test` for "instead of"), numbered N_POSES + 1, N_POSES + 2, ...
    in file order, and join train or test by their split tag (`numbers`). Every camera is perturbed
    by N(0, position_sigma_m) per axis and N(0, angle_sigma_rad) per angle (allo_usd.scene.rig.perturb)."""

    train: list[int] = Field(default_factory=lambda: list(range(1, 41)), description="Training poses.")
    test: list[int] = Field(default_factory=lambda: list(range(41, 51)), description="Test poses.")
    file: str | None = Field(None, description="A pose file (.csv or .json) of the user's own poses, relative to "
                                               "the working directory; see docs/guide/bring_your_own.md, "
                                               "Your own poses.")
    position_sigma_m: float = Field(1.0, ge=0.0, le=10.0, description="Camera position perturbation sigma per "
                                                                      "axis, metres (the paper: 1).")
    angle_sigma_rad: float = Field(0.2, ge=0.0, le=1.0, description="Camera angle perturbation sigma per "
                                                                    "Euler angle, radians (the paper: 0.2).")

    @field_validator("file")
    @classmethod
    def _file(cls, v: str | None):
        if v is not None and ("\0" in v or not v.lower().endswith((".csv", ".json"))):
            raise ValueError(f"poses.file {_short(v)} is not a .csv or .json file path; fix: e.g. my_poses.csv")
        return v

    def pose_file(self):
        """The pose file read (allo_usd.plan.posefile.PoseFile), or None without one."""
        from allo_usd.plan.posefile import read_pose_file

        return None if self.file is None else read_pose_file(self.file)

    def file_poses(self) -> list[tuple[int, object]]:
        """(pose number, UserPose) of the pose file's poses: N_POSES + 1, ... in file order."""
        f = self.pose_file()
        return [] if f is None else [(N_POSES + 1 + i, p) for i, p in enumerate(f.poses)]

    def numbers(self, split: str) -> list[int]:
        """Every pose number of `split` (train | test): the built-in ones listed, then the file's."""
        return [*getattr(self, split), *(n for n, p in self.file_poses() if p.split == split)]

    @field_validator("train", "test")
    @classmethod
    def _range(cls, v: list[int]) -> list[int]:
        bad = [p for p in v if not 1 <= p <= N_POSES]
        if bad:
            raise ValueError(f"pose numbers {_short(bad)} are outside 1..{N_POSES}; fix: use base poses 1..{N_POSES}")
        if len(set(v)) != len(v):
            raise ValueError("a pose is listed twice; fix: list each pose once")
        return sorted(v)

    @model_validator(mode="after")
    def _disjoint(self):
        both = sorted(set(self.train) & set(self.test))
        if both:
            raise ValueError(f"poses {both} are in both train and test; fix: make the sets disjoint "
                             "(the paper uses 1-40 for train and 41-50 for test)")
        if not self.numbers("train") and not self.numbers("test"):
            raise ValueError("no poses; fix: list at least one train or test pose, or give a pose file")
        return self


HAZARD_USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")   # a USD hazard: its own metersPerUnit and upAxis
HAZARD_SUFFIXES = (*SUPPORTED_EXTENSIONS, *HAZARD_USD_SUFFIXES)   # a user hazard's model file
HAZARD_ID = r"^[a-z][a-z0-9_]{0,47}$"     # a USD prim name, a dataset folder name, one spelling (lower case)
HAZARD_UNITS = tuple(UNIT_SCALES)
HAZARD_UP_AXES = tuple(UP_AXIS_ROTATIONS)
RESERVED_HAZARD_IDS = ("good", "anomaly", "station", "background")   # dataset folders and class names
USER_VARIANT = "default"                  # a user hazard's variant with the file's own materials
MAX_HAZARD_COLORS = 32


class AnomalyChoice(_Model):
    """One anomaly asset and the variants to draw from (None: all its variants).

    A built-in asset is named by its id alone. Your own hazard adds `file`, a glTF/GLB, OBJ, STL
    or USD model converted when the plan is authored (allo_usd.usd.hazard, the importer of
    `allo-usd asset import`), with its length unit and up axis given (`units`, `up_axis`; a USD
    file's own metersPerUnit and upAxis are used when these are left out) and optional `colors`:
    named linear-RGB variants that set every material's base colour (textures are multiplied by
    it). Its variants are `default` (the file's own materials) and the colour names."""

    id: str = Field(description="A built-in asset id (allo_usd.assets.catalogue.ANOMALY_VARIANTS), or, with "
                                "`file`, your hazard's id: lower case letters, digits and _, not a built-in id.")
    variants: list[str] | None = Field(None, description="Variants to cycle through; default all.")
    file: str | None = Field(None, description="Your hazard's model: a " + ", ".join(HAZARD_SUFFIXES) + " file "
                                               "(relative to the working directory).")
    units: Literal[HAZARD_UNITS] | None = Field(None, description="The file's length unit: "
                                                + ", ".join(HAZARD_UNITS) + " (required for non-USD files).")
    up_axis: Literal[HAZARD_UP_AXES] | None = Field(
        None, description="The file axis that points up: " + ", ".join(HAZARD_UP_AXES)
                          + " (required for non-USD files).")
    colors: dict[str, tuple[float, float, float]] | None = Field(
        None, description="Colour variants: name -> linear RGB in 0..1, set as every material's base colour.")

    @model_validator(mode="before")
    @classmethod
    def _from_string(cls, v):
        if isinstance(v, str):  # "wrench" or "wrench:chrome"
            name, _, variant = v.partition(":")
            return {"id": name, "variants": [variant] if variant else None}
        return v

    @field_validator("up_axis", mode="before")
    @classmethod
    def _axis(cls, v):
        return v.strip().lower().lstrip("+") if isinstance(v, str) else v   # "Y", "+Z" -> "y", "z"

    @model_validator(mode="after")
    def _known(self):
        from allo_usd.assets.catalogue import ANOMALY_VARIANTS

        if self.file is not None:
            return self._user_hazard()
        given = [f for f in ("units", "up_axis", "colors") if getattr(self, f) is not None]
        if given and self.id in ANOMALY_VARIANTS:
            raise ValueError(f"anomaly {self.id!r} is built in, so it takes no {', '.join(given)}; fix: remove them, "
                             "or give your own hazard another id and its `file`")
        if self.id not in ANOMALY_VARIANTS:
            raise ValueError(f"unknown anomaly id {_short(self.id)}; fix: use one of {', '.join(ANOMALY_VARIANTS)}, "
                             "or add `file = \"path/to/model.glb\"` (with units and up_axis) for your own hazard")
        bad = [v for v in self.variants or () if v not in ANOMALY_VARIANTS[self.id]]
        if bad:
            raise ValueError(f"anomaly {self.id!r} has no variant {_short(bad)}; fix: use one of "
                             f"{', '.join(ANOMALY_VARIANTS[self.id])}")
        return self

    def _user_hazard(self):
        import math
        import re

        from allo_usd.assets.catalogue import ANOMALY_VARIANTS

        if not re.fullmatch(HAZARD_ID, self.id) or self.id in RESERVED_HAZARD_IDS:
            raise ValueError(f"hazard id {_short(self.id)} is not allowed; fix: use lower case letters, digits and _ "
                             f"(a letter first, at most 48), not {', '.join(RESERVED_HAZARD_IDS)}: it names a USD prim "
                             "and a dataset folder")
        if self.id in ANOMALY_VARIANTS:
            raise ValueError(f"hazard id {self.id!r} is a built-in anomaly's; fix: give your hazard another id")
        f = self.file
        if not f or "\0" in f or not f.lower().endswith(HAZARD_SUFFIXES):
            raise ValueError(f"anomaly {self.id!r}: file {_short(f)} is not a model file; fix: give a path ending in "
                             + ", ".join(HAZARD_SUFFIXES))
        if not f.lower().endswith(HAZARD_USD_SUFFIXES) and (self.units is None or self.up_axis is None):
            missing = " and ".join(n for n in ("units", "up_axis") if getattr(self, n) is None)
            raise ValueError(f"anomaly {self.id!r}: {f} needs {missing} given (a mesh file does not say reliably "
                             "which unit and axis it uses); fix: e.g. units = \"mm\", up_axis = \"z\"")
        if len(self.colors or {}) > MAX_HAZARD_COLORS:
            raise ValueError(f"anomaly {self.id!r} has {len(self.colors)} colour variants, above the "
                             f"{MAX_HAZARD_COLORS} a hazard may have (each is a geometry file in the tree); fix: "
                             "keep the colours you train on")
        for name, rgb in (self.colors or {}).items():
            if not re.fullmatch(r"^[a-z][a-z0-9_]{0,31}$", name) or name == USER_VARIANT:
                raise ValueError(f"anomaly {self.id!r}: colour variant name {_short(name)} is not allowed; fix: lower "
                                 f"case letters, digits and _ (a letter first), not {USER_VARIANT!r} (the file's own "
                                 "materials)")
            if not all(math.isfinite(c) and 0.0 <= c <= 1.0 for c in rgb):
                raise ValueError(f"anomaly {self.id!r}: colour {name!r} = {_short(rgb)} is not a linear RGB colour; "
                                 "fix: three numbers in 0..1, e.g. [0.8, 0.05, 0.05]")
        allowed = self.user_variants()
        bad = [v for v in self.variants or () if v not in allowed]
        if bad:
            names = ", ".join(_short(v) for v in bad[:5]) + (", ..." if len(bad) > 5 else "")
            colours = (f"colors defines {', '.join(repr(c) for c in self.colors)}" if self.colors
                       else "the plan gives it no colors")
            example = bad[0] if isinstance(bad[0], str) and re.fullmatch(r"^[a-z][a-z0-9_]{0,31}$", bad[0]) else "red"
            raise ValueError(f"anomaly {self.id!r}: variant{'s' if len(bad) > 1 else ''} {names} "
                             f"{'are' if len(bad) > 1 else 'is'} not defined: a hazard of your own has the variant "
                             f"{USER_VARIANT!r} (the file's own materials) and one per name in its colors, and "
                             f"{colours}; fix: define {'them' if len(bad) > 1 else 'it'} in colors, e.g. colors = "
                             f"{{ {example} = [0.8, 0.05, 0.05] }} (linear RGB in 0..1), or leave "
                             f"{'them' if len(bad) > 1 else 'it'} out of variants")
        if self.variants is not None and not self.variants:
            raise ValueError(f"anomaly {self.id!r}: variants is empty; fix: list some of {', '.join(allowed)}, or leave "
                             "variants out for all")
        twice = sorted({v for v in self.variants or () if self.variants.count(v) > 1})
        if twice:
            raise ValueError(f"anomaly {self.id!r}: variant {_short(twice[0])} is listed twice in variants; fix: list "
                             "each once")
        return self

    def user_variants(self) -> tuple[str, ...]:
        """A user hazard's variants: the file's own materials, then each colour (in the plan's order)."""
        return (USER_VARIANT, *(self.colors or {}))

    def choices(self) -> list[tuple[str, str]]:
        from allo_usd.assets.catalogue import ANOMALY_VARIANTS

        names = self.user_variants() if self.file is not None else ANOMALY_VARIANTS[self.id]
        return [(self.id, v) for v in (self.variants or names)]


def _all_anomalies() -> list[AnomalyChoice]:
    from allo_usd.assets.catalogue import ANOMALY_IDS

    return [AnomalyChoice(id=a) for a in ANOMALY_IDS]


class Anomalies(_Model):
    """Which anomalies to insert and at which depths (indices into placement.DEPTH_OFFSETS)."""

    assets: list[AnomalyChoice] = Field(default_factory=_all_anomalies, description="Default: all 16.")
    depths: list[int] = Field(default_factory=lambda: list(range(DEPTH_COUNT)),
                              description="Depth indices 0..4 = offsets 0, -1, +1, -2, +2 m.")
    reserve_groups_per_slot: int = Field(
        3, ge=0, le=100,
        description="Top-up bound: a (seed, asset, variant) whose planned depths were skipped may draw at "
                    "most this many reserve placement groups per skipped depth to fill them; 0 turns the "
                    "top-up off (see allo_usd.plan.enumeration.reserve_group).")

    @field_validator("depths")
    @classmethod
    def _depths(cls, v: list[int]) -> list[int]:
        if not v or any(not 0 <= d < DEPTH_COUNT for d in v) or len(set(v)) != len(v):
            raise ValueError(f"depths {_short(v)} must be distinct indices in 0..{DEPTH_COUNT - 1}; "
                             "fix: e.g. [0, 1, 2, 3, 4]")
        return sorted(v)

    @field_validator("assets")
    @classmethod
    def _assets(cls, v: list[AnomalyChoice]) -> list[AnomalyChoice]:
        ids = [a.id for a in v]
        if len(set(ids)) != len(ids):
            twice = next(i for n, i in enumerate(ids) if i in ids[:n])
            demo = " (a plan from `allo-usd plan --demo` lists it already)" if twice == "power_drill" else ""
            raise ValueError(f"anomaly id {_short(twice)} is listed twice{demo}; fix: list each id once, with its "
                             "variants")
        return v

    def user_hazards(self) -> list[AnomalyChoice]:
        """The plan's own hazards (those with a `file`), in plan order."""
        return [a for a in self.assets if a.file is not None]


class Counts(_Model):
    """How many images of each kind; None means the full grid (every day x pose x seed).

    A count below the grid takes a seeded subset (see `enumerate_scenes`). Anomalous images come
    in placements of `len(depths)` images; a count that is not a multiple drops the last depths.
    """

    normal_train: int | None = Field(None, ge=0)
    normal_test: int | None = Field(None, ge=0)
    anomalous_test: int | None = Field(None, ge=0)


# Effects and Quality take their fields' defaults from allo_usd.plan.settings.EffectFlags and
# QualitySettings, the one declaration; tests/plan/test_settings.py checks the field names agree.
class Effects(_Model):
    """Mirrors allo_usd.scene.spec.EffectsSpec: what each scene asks the renderer to simulate."""

    sensor_noise: bool = EffectFlags.sensor_noise
    glare: bool = EffectFlags.glare
    inspection_light: bool = EffectFlags.inspection_light
    body_shine: bool = EffectFlags.body_shine


class Quality(_Model):
    """Render quality. `preset` (one of allo_usd.plan.settings.PRESETS) fills every quality field the
    plan leaves out; a field the plan sets wins. The model remembers which fields were set
    (`model_fields_set`), and a written plan records only those, so editing the preset of a written
    plan changes every field it did not set."""

    preset: Literal[tuple(PRESETS)] = Field(
        "preview", description="The render preset that fills the fields left out: " + ", ".join(PRESETS) + ".")
    resolution: tuple[int, int] = Field((1920, 1080), description="Width, height in pixels.")
    samples: int = Field(QualitySettings.samples, description="Path-tracing samples per pixel, 1..65536.")
    denoise: bool = QualitySettings.denoise
    denoise_prefilter: Literal[DENOISE_PREFILTERS] = QualitySettings.denoise_prefilter
    denoise_quality: Literal[DENOISE_QUALITIES] = QualitySettings.denoise_quality
    max_bounces: int = Field(QualitySettings.max_bounces, ge=0, le=1024)
    adaptive_threshold: float = Field(QualitySettings.adaptive_threshold, ge=0.0, le=1.0)
    target_psnr: float = Field(QualitySettings.target_psnr, description=(
        "Target mode: spend samples in rounds of two independent halves until the estimated PSNR of the delivered "
        "image (8-bit sRGB, against the converged image) reaches this many dB, in (0, 100]; `samples` caps the "
        "samples per pixel (both halves together) and time_limit the seconds, and each render's JSON records which "
        "stopped it. 0: fixed samples (every named preset). `render --target-psnr` overrides it for a run."))
    time_limit: float = Field(QualitySettings.time_limit, description=(
        "Target mode: seconds after which a render stops spending samples, 0..1e6 (0: no limit); only with "
        "target_psnr."))
    passes: list[str] = Field(list(DEFAULT_PASSES), json_schema_extra={"items": {"enum": list(PASSES)}},
                              description="The files each scene writes, recorded in its layer as UsdRender vars: "
                                          + ", ".join(PASSES) + " (docs/formats/render_outputs.md, Passes); "
                                          "`render --passes` overrides them for a run. Without rgb and exr a scene renders 1 sample.")

    @field_validator("passes")
    @classmethod
    def _passes(cls, v):
        problem = passes_problem(v)
        if problem:
            raise ValueError(f"{problem}; fix: e.g. passes = [\"rgb\", \"exr\", \"mask\", \"depth\"]")
        return [p for p in PASSES if p in v]

    @model_validator(mode="wrap")
    @classmethod
    def _fill_from_preset(cls, data, handler):
        """The preset's values under the given ones; afterwards only the given fields count as set."""
        if not isinstance(data, dict):
            return handler(data)
        preset = data.get("preset", "preview")
        fill = PRESETS.get(preset, {}) if isinstance(preset, str) else {}   # an unknown name fails as a Literal
        given = {k for k in data if k in cls.model_fields}
        quality = handler({**fill, **data})
        object.__setattr__(quality, "__pydantic_fields_set__", given)   # what save_plan writes
        return quality

    @field_validator("resolution")
    @classmethod
    def _resolution(cls, v):
        problem = resolution_problem(*v)
        if problem:
            raise ValueError(f"{problem}; fix: e.g. [1920, 1080]")
        return v

    @field_validator("samples")
    @classmethod
    def _samples(cls, v):
        if not 1 <= v <= 65536:
            raise ValueError(f"samples={v} is outside 1..65536; fix: e.g. 64")
        return v

    @model_validator(mode="after")
    def _target(self):
        problem = target_problem(self.target_psnr, self.time_limit)   # the error names the quality table
        if problem:
            raise ValueError(problem)
        return self


class Render(_Model):
    """How this plan's scenes are rendered, not what they show: never written into a layer (a scene
    rendered on another device means the same), so a tree's plan comparison leaves it out
    (allo_usd.run.author_tree.UNCOMPARED) and `render --device` overrides it for a run."""

    device: str = Field("auto", description="The Cycles device: auto (a GPU when Cycles finds one, else the CPU "
                                            "with a one-line notice), cpu (never probes for a GPU), gpu (fails "
                                            "when there is none).",
                        json_schema_extra={"enum": list(DEVICES)})

    @field_validator("device", mode="before")
    @classmethod
    def _device(cls, v):
        if v not in DEVICES:   # exactly as the schema's enum says
            raise ValueError(f"device {_short(v)} is not a render device; fix: use one of {', '.join(DEVICES)}")
        return v


class Station(_Model):
    """'procedural' (the built-in station) or the path of a glTF/OBJ/STL model the base stage is built from.

    The model's orientation and units come from the file or from these fields, never from its name:
    'auto' is what the format says (glTF: +Y up and metres by specification; OBJ: Y up by convention;
    STL: Z up) and, for units, the size heuristic of allo_usd.assets.importer. A file that breaks its
    format's rule (NASA's ISS_2016.glb is in inches with +Z nadir) needs `units` and `up_axis` given."""

    source: str = "procedural"
    units: Literal[STATION_UNITS] = Field("auto", description="The model's length unit: "
                                          + ", ".join(STATION_UNITS) + ".")
    up_axis: Literal[STATION_UP_AXES] = Field(
        "auto", description="The model axis that points up (zenith): " + ", ".join(STATION_UP_AXES)
                            + "; 'auto' is the format's own (glTF, OBJ: y; STL: z).")
    track_sun: bool = Field(False, description="Turn the procedural station's solar arrays (alpha and beta "
                            "joints) to face each day's Sun, within the joints' limits; off keeps the rest pose "
                            "(the paper's). Only for source = 'procedural'.")

    @field_validator("up_axis", mode="before")
    @classmethod
    def _axis(cls, v):
        return v.strip().lower().lstrip("+") if isinstance(v, str) else v   # "Y", "+Z" -> "y", "z"

    @field_validator("source")
    @classmethod
    def _source(cls, v):
        if (v != "procedural" and not v.lower().endswith(STATION_SUFFIXES)) or "\0" in v:
            raise ValueError(f"station source {_short(v)} is neither 'procedural' nor a model file; fix: use "
                             f"'procedural' or a path ending in {', '.join(STATION_SUFFIXES)}")
        return v

    @model_validator(mode="after")
    def _tracking(self):
        if self.track_sun and self.source != "procedural":
            raise ValueError(f"station.track_sun is on but station.source is the model {_short(self.source)}; only "
                             "the procedural station has solar-array joints; fix: set track_sun = false or "
                             "source = 'procedural'")
        return self


def _in(name: str, v: float, bounds: tuple[float, float], unit: str, example: str) -> float:
    if not bounds[0] <= v <= bounds[1]:
        raise ValueError(f"{name} = {v:g} {unit} is outside {bounds[0]:g}..{bounds[1]:g} {unit} (what the layer "
                         f"reader passes to Blender); fix: e.g. {example}")
    return v


class Camera(_Model):
    """The lens and sensor (`[camera]`); every field left out is the paper's Table I (25 mm lens,
    36 x 20.25 mm sensor, clipping 0.05 m .. 1e12 m, principal point at the image centre). Pixels are
    square and the fit horizontal: give the sensor's width or its height, the other follows from the
    resolution's aspect. Authored on /World/Camera as UsdGeom.Camera values (core.camera_model)."""

    focal_length_mm: float = Field(DEFAULT_CAMERA.focal_length_mm, allow_inf_nan=False,
                                   description="Focal length in mm.")
    sensor_width_mm: float | None = Field(None, allow_inf_nan=False,
                                          description="Sensor (horizontal aperture) width in mm; default 36.")
    sensor_height_mm: float | None = Field(None, allow_inf_nan=False,
                                           description="Sensor height in mm (instead of the width).")
    resolution: tuple[int, int] | None = Field(None, description="Width, height in pixels; default "
                                               "quality.resolution (give one of the two, or the same).")
    clipping_range_m: tuple[float, float] = Field(DEFAULT_CAMERA.clipping_range_m,
                                                  description="Near, far clipping distances in metres.")
    principal_point_offset_px: tuple[float, float] = Field(
        (0.0, 0.0), description="Principal point in pixels from the image centre (x right, y down), within the image.")

    @field_validator("focal_length_mm")
    @classmethod
    def _focal(cls, v):
        return _in("focal_length_mm", v, LENS_MM, "mm", "focal_length_mm = 25")

    @field_validator("sensor_width_mm", "sensor_height_mm")
    @classmethod
    def _sensor(cls, v, info):
        return v if v is None else _in(info.field_name, v, SENSOR_MM, "mm", f"{info.field_name} = 36")

    @field_validator("clipping_range_m")
    @classmethod
    def _clip(cls, v):
        near, far = v
        if not CLIP_M[0] <= near < far <= CLIP_M[1]:
            raise ValueError(f"clipping_range_m = ({near:g}, {far:g}) must be near < far within {CLIP_M[0]:g}..{CLIP_M[1]:g} m "
                             "(what the layer reader passes to Blender); fix: e.g. clipping_range_m = [0.05, 1e12]")
        import numpy as np

        if not np.float32(near) < np.float32(far):   # the layer stores them as float32 (UsdGeom.Camera's float2)
            raise ValueError(f"clipping_range_m = ({near!r}, {far!r}): near and far are the same number as the layer "
                             "stores them (32-bit floats, about 7 digits), so the reader would refuse every scene; "
                             "fix: move far further from near, e.g. far = 2 x near")
        return v

    @field_validator("principal_point_offset_px")
    @classmethod
    def _offset(cls, v):
        if not all(math.isfinite(x) for x in v):
            raise ValueError(f"principal_point_offset_px = {_short(v)} is not finite; fix: e.g. [0, 0]")
        return v

    @field_validator("resolution")
    @classmethod
    def _resolution(cls, v):
        problem = v and resolution_problem(*v)
        if problem:
            raise ValueError(f"{problem}; fix: e.g. resolution = [1920, 1080]")
        return v

    def model(self, size: tuple[int, int]) -> CameraModel:
        """The lens for a `size` = (width, height) image; raises ValueError naming the field and the fix."""
        w, h = size
        sw, sh = self.sensor_width_mm, self.sensor_height_mm
        if sw is None and sh is None:   # Table I's 36 mm width, as the base stage; the height the image's aspect gives
            sw, sh = DEFAULT_CAMERA.sensor_width_mm, sensor_height_for(DEFAULT_CAMERA.sensor_width_mm, w, h)
        elif sh is None:
            sh = sw * h / w
        elif sw is None:
            sw = sh * w / h
        elif abs(sw * h - sh * w) > 1e-6 * sw * h:
            raise ValueError(f"camera.sensor_width_mm = {sw:g} and sensor_height_mm = {sh:g} (aspect {sw / sh:.6g}) "
                             f"do not match the {w}x{h} image (aspect {w / h:.6g}) with square pixels; fix: give only "
                             f"one of them, or sensor_height_mm = {sw * h / w:g}")
        for name, v in (("sensor_width_mm", sw), ("sensor_height_mm", sh)):
            _in(f"camera.{name} (from the other and the {w}x{h} aspect)", v, SENSOR_MM, "mm",
                "a sensor size nearer the image's aspect")
        dx, dy = self.principal_point_offset_px
        if abs(dx) > w / 2 or abs(dy) > h / 2:
            raise ValueError(f"camera.principal_point_offset_px = ({dx:g}, {dy:g}) puts the principal point outside "
                             f"the {w}x{h} image (|dx| <= {w / 2:g}, |dy| <= {h / 2:g}); fix: give an offset within it")
        return CameraModel(float(self.focal_length_mm), float(sw), float(sh),
                           tuple(map(float, self.clipping_range_m)), (float(dx) + 0.0, float(dy) + 0.0))


class Plan(_Model):
    """A whole dataset: every field has a default, so `Plan(name="x")` is a valid (full-grid) plan."""

    name: str = Field(min_length=1, max_length=100, pattern=r"^[A-Za-z0-9_.-]+$")
    dates: Dates = Field(default_factory=Dates)
    perilune_epoch: datetime = Field(datetime(2030, 1, 1, tzinfo=timezone.utc),
                                     description="UTC instant of the orbit's perilune passage.")
    poses: Poses = Field(default_factory=Poses)
    anomalies: Anomalies = Field(default_factory=Anomalies)
    counts: Counts = Field(default_factory=Counts)
    effects: Effects = Field(default_factory=Effects)
    quality: Quality = Field(default_factory=Quality)
    render: Render = Field(default_factory=Render)
    seeds: list[int] = Field(default_factory=lambda: [2030], description="One pipeline run per seed.")
    station: Station = Field(default_factory=Station)
    base_stage: str = Field("stages/base.usda", description="Relative to the working directory, else to the package's data (stages/base.usda is the shipped base stage).")
    camera: Camera = Field(default_factory=Camera, description="The lens and sensor; defaults: the paper's Table I.")

    @model_validator(mode="before")
    @classmethod
    def _camera_resolution(cls, data):
        """camera.resolution fills quality.resolution when the plan leaves that out (so the render uses it)."""
        if not isinstance(data, dict):
            return data
        cam = data.get("camera")
        res = cam.get("resolution") if isinstance(cam, dict) else getattr(cam, "resolution", None)
        q = data.get("quality", {})
        if res is None:
            return data
        if isinstance(q, Quality):
            if "resolution" in q.model_fields_set:
                return data
            q = {k: getattr(q, k) for k in q.model_fields_set}
        if not isinstance(q, dict) or "resolution" in q:
            return data
        return {**data, "quality": {**q, "resolution": res}}

    @model_validator(mode="after")
    def _camera_fits(self):
        res = self.camera.resolution
        if res is not None and tuple(res) != tuple(self.quality.resolution):
            raise ValueError(f"camera.resolution {list(res)} differs from quality.resolution "
                             f"{list(self.quality.resolution)}; fix: give the resolution in one of them, or the same "
                             "in both")
        self.camera.model(self.quality.resolution)   # the sensor's aspect and the offset against the image
        return self

    @model_validator(mode="after")
    def _target_without_glare(self):
        from allo_usd.plan.settings import TARGET_WITH_GLARE

        if self.quality.target_psnr > 0 and self.effects.glare:
            raise ValueError("quality.target_psnr with effects.glare: " + TARGET_WITH_GLARE)
        return self

    def camera_model(self) -> tuple[CameraModel, tuple[int, int]]:
        """(the plan's lens, the image size (width, height)) it renders with."""
        size = tuple(int(v) for v in self.quality.resolution)
        try:
            return self.camera.model(size), size
        except ValueError as exc:
            raise PlanError(str(exc)) from None

    @field_validator("perilune_epoch", mode="before")
    @classmethod
    def _parse(cls, v):
        """Text is read by the one parser of recorded times (allo_usd.core.timefmt)."""
        if isinstance(v, str):
            try:
                return parse_utc(v, "perilune_epoch")
            except EpochError as exc:
                raise ValueError(str(exc)) from None
        return v

    @field_serializer("perilune_epoch")
    def _record(self, v: datetime) -> str:
        return format_utc(v)

    @field_validator("perilune_epoch")
    @classmethod
    def _aware(cls, v: datetime):
        if v.tzinfo is None:
            raise ValueError("perilune_epoch has no timezone; fix: write it in UTC, e.g. 2030-01-01T00:00:00Z")
        try:
            return v.astimezone(timezone.utc)
        except OverflowError:   # 9999-12-31T23:00-05:00 is past the calendar's end in UTC
            raise ValueError(f"perilune_epoch {v.isoformat()} is outside the calendar in UTC; fix: write a UTC "
                             "instant, e.g. 2030-01-01T00:00:00Z") from None

    @field_validator("seeds")
    @classmethod
    def _seeds(cls, v: list[int]):
        if not v or len(set(v)) != len(v) or any(s < 0 for s in v):
            raise ValueError(f"seeds {_short(v)} must be a non-empty list of distinct non-negative integers; "
                             "fix: e.g. [2030, 2031]")
        return v

    @field_validator("base_stage")
    @classmethod
    def _path(cls, v: str):
        if "\0" in v or not v:
            raise ValueError(f"base_stage {_short(v)} is not a file path; fix: e.g. stages/base.usda")
        return v

    @model_validator(mode="after")
    def _counts_fit(self):
        grid = grid_sizes(self)
        for name in ("normal_train", "normal_test"):
            if grid[name] > MAX_PLAN_SCENES:
                raise ValueError(f"the {name} grid (days x seeds x poses) holds {grid[name]:,} scenes, above the "
                                 f"{MAX_PLAN_SCENES:,} a plan may draw from; fix: fewer days, seeds or poses, or "
                                 "split the dataset into several plans")
        for name, n in (("normal_train", self.counts.normal_train), ("normal_test", self.counts.normal_test),
                        ("anomalous_test", self.counts.anomalous_test)):
            if n is not None and n > grid[name]:
                raise ValueError(f"counts.{name}={n} exceeds the {grid[name]} scenes the days, poses, seeds "
                                 f"(and depths) allow; fix: lower it or add days/poses/seeds")
        n = sum(planned_sizes(self).values())
        if n > MAX_PLAN_SCENES:
            raise ValueError(f"the plan expands to {n:,} scenes, above the {MAX_PLAN_SCENES:,} one plan may hold; "
                             "fix: set counts, or fewer days, seeds, poses or depths, or split the dataset into "
                             "several plans")
        return self

    def resolve_base_stage(self) -> Path:
        from allo_usd.core.paths import DATA

        p = Path(self.base_stage)
        for cand in (p, DATA / p):
            if cand.is_file():
                return cand.resolve()
        raise PlanError(f"base_stage: {self.base_stage} does not exist; fix: run scripts/make_base_stage.py "
                        "or point base_stage at a base.usda")


def grid_sizes(plan: Plan) -> dict[str, int]:
    """The scenes of each kind the plan's days, poses, seeds (and depths) allow."""
    n = plan.dates.days * len(plan.seeds)
    train, test = len(plan.poses.numbers("train")), len(plan.poses.numbers("test"))
    return {"normal_train": n * train, "normal_test": n * test,
            "anomalous_test": n * test * len(plan.anomalies.depths) if plan.anomalies.assets else 0}


def planned_sizes(plan: Plan) -> dict[str, int]:
    """The scenes of each kind `enumerate_scenes` gives, by arithmetic: the count, or the full grid
    (a validated plan's counts never exceed its grid)."""
    grid = grid_sizes(plan)
    return {name: n if (n := getattr(plan.counts, name)) is not None else grid[name] for name in grid}


# ---------------------------------------------------------------------------------------------
# The paper's plan and scene enumeration


def paper_plan() -> Plan:
    """ALLO paper Table II: 29,085 normal train, 7,300 normal test, 15,024 anomalous test images.

    365 days of 2030 (00:00 UTC), poses 1-40 train and 41-50 test, two seeds (the paper runs
    the pipeline twice). How `enumerate_scenes` reaches the counts exactly:
    - normal train: the grid is 365 x 40 x 2 = 29,200; a seeded subset of 29,085 is kept
      (115 (seed, day, pose) triples dropped);
    - normal test: 365 x 10 x 2 = 7,300, the full grid;
    - anomalous test: 15,024 = 5 x 3,005 - 1. The paper's count is not a multiple of its five
      depths, which we read as one depth skipped; so 3,005 placements are drawn (1,503 for the
      first seed, 1,502 for the second; each a seeded (day, test pose) with an anomaly assigned
      round-robin over the 16 assets and their variants), and the last placement keeps only
      depths 0-3. Depths that the ray-cast check skips when authoring are recorded in
      skipped.csv and topped up from reserve groups of the same (seed, asset, variant)
      (`reserve_group`; allo_usd.run.topup), so each asset keeps its planned share of the 15,024.
    """
    return Plan(name="allo-paper", dates=Dates(start=date(2030, 1, 1), days=365, step_days=1),
                counts=Counts(normal_train=29_085, normal_test=7_300, anomalous_test=15_024),
                seeds=[2030, 2031], quality=Quality(preset="final", resolution=(1920, 1080)))


def demo_plan() -> Plan:
    """A tiny plan for trying the pipeline: 2 days, 2 train poses, 1 test pose, 1 anomaly, 5 depths."""
    return Plan(name="demo", dates=Dates(days=2), poses=Poses(train=[1, 2], test=[41]),
                anomalies=Anomalies(assets=[AnomalyChoice(id="power_drill")]), station=Station(track_sun=True),
                quality=Quality(preset="demo", resolution=(480, 270)))
