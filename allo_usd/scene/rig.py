"""Camera rig: 50 base poses around the station and the paper's seeded perturbation.

Base poses are chosen, not hand-aimed: every candidate position (exterior fixture points, and
points 1-2.5 m off the station's surface) is tried with 96 look directions, and each view is
ray cast on a coarse grid over the image (`view_quality`). A view qualifies when its centre ray
and most of its structure lie 5-40 m away, the structure neither leaves the frame nearly empty
nor fills it like a wall, and little of the frame is closer than 5 m. The best view of each
position is kept; positions are then taken greedily by view score, at least `MIN_SPACING_M`
apart. Poses 41-50 (test) are taken first, and every training position (poses 1-40) keeps at
least `TEST_SEPARATION_M` (8 m) from every test position, so after the N(0, 1 m) perturbation
train and test cameras still stand in different places; a training camera within
`TEST_NEIGHBOUR_M` (16 m) of a test camera also looks at least `TEST_TURN_DEG` (30 degrees) away
from it, so the two never show the same structure from a few metres apart.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from allo_usd.scene.spec import CameraPose
from allo_usd.core.errors import PlacementError
from allo_usd.core.camera_model import DEFAULT_CAMERA, CameraModel
from allo_usd.core.geometry import check_finite, fibonacci_sphere, look_at, rot_x, rot_y, rot_z
from allo_usd.scene.raycast import RayFan, RayScene
from allo_usd.core import fixedmath as fm

N_TRAIN, N_TEST = 40, 10
POSITION_SIGMA_M = 1.0
ANGLE_SIGMA_RAD = 0.2
PERTURBATION = "euler-zyx-local"  # R = R_base @ Rz(yaw) @ Ry(pitch) @ Rx(roll), angles ~ N(0, 0.2)
CLEARANCE_M = 0.3
RIG_SEED = 50

VIEW_RANGE_M = (5.0, 40.0)     # structure a base pose looks at
COVERAGE_RANGE = (0.2, 0.9)    # fraction of the frame showing structure: not empty, not a wall
MIN_IN_RANGE = 0.75            # of the rays that hit structure, this many are 5-40 m away
MAX_NEAR = 0.1                 # at most this fraction of the frame is structure under 5 m
MIN_SPACING_M = 4.0            # between any two base positions
TEST_SEPARATION_M = 8.0        # between every test position and every training position
TEST_NEIGHBOUR_M, TEST_TURN_DEG = 16.0, 30.0   # a training camera within 16 m of a test camera looks
                                               # at least 30 degrees away from it
QUALITY_GRID = (32, 18)        # rays across x down the image for `view_quality`
_SCREEN_GRID = (16, 9)         # the cheaper grid every candidate direction is screened with
_N_DIRECTIONS = 96
_REFINE = 4                    # best screened directions per position re-checked on QUALITY_GRID


@dataclass(frozen=True)
class ViewQuality:
    """What a camera sees, from rays through a grid of image points and the optical axis."""

    centre_m: float       # distance along the optical axis to the first structure (inf: none)
    coverage: float       # fraction of grid rays that hit structure
    in_range: float       # of those, the fraction 5-40 m away
    near: float           # fraction of grid rays hitting structure closer than 5 m

    @property
    def ok(self) -> bool:
        lo, hi = VIEW_RANGE_M
        return bool(lo <= self.centre_m <= hi and COVERAGE_RANGE[0] <= self.coverage <= COVERAGE_RANGE[1]
                    and self.in_range >= MIN_IN_RANGE and self.near <= MAX_NEAR)

    @property
    def value(self) -> float:
        """How good the view is, qualifying or not: the fraction of the frame showing structure
        5-40 m away, less 1.5x what exceeds 70% coverage (keep some space in view), less twice
        what is nearer than 5 m, less 0.5 when the optical axis misses the 5-40 m range."""
        lo, hi = VIEW_RANGE_M
        return (self.coverage * self.in_range - 1.5 * max(0.0, self.coverage - 0.7) - 2.0 * self.near
                - (0.0 if lo <= self.centre_m <= hi else 0.5))

    @property
    def score(self) -> float:
        """`value` for a qualifying view, -1 otherwise."""
        return self.value if self.ok else -1.0


def image_grid(nx: int, ny: int, lens: CameraModel = DEFAULT_CAMERA, size: tuple[int, int] | None = None
               ) -> np.ndarray:
    """(nx * ny + 1, 3) camera-frame ray directions: the centres of an nx x ny grid of cells over
    the image `lens` sees (default the paper's 36 x 20.25 mm sensor behind 25 mm), row-major from the
    top left, then the optical axis (0, 0, -1). `size`: the image's (width, height) in pixels, which
    the lens's principal point offset is counted in (the window moves by -dx/f, +dy/f in x/-z, y/-z);
    None: no offset."""
    tx, ty = lens.half_tangents()
    ox, oy = (0.0, 0.0) if size is None else lens.window_centre(size[0])
    x = ((np.arange(nx) + 0.5) / nx * 2 - 1) * tx + ox
    y = (1 - (np.arange(ny) + 0.5) / ny * 2) * ty + oy
    gx, gy = np.meshgrid(x, y)
    d = np.stack([gx.ravel(), gy.ravel(), -np.ones(gx.size)], axis=1)
    return np.concatenate([d, [[0.0, 0.0, -1.0]]])


def _qualities(station: RayScene, position, rotations: np.ndarray, grid, lens: CameraModel = DEFAULT_CAMERA,
               size: tuple[int, int] | None = None) -> list[ViewQuality]:
    local = image_grid(*grid, lens, size)
    d = fm.dot(rotations[:, None, :, :], local[None, :, None, :]).reshape(-1, 3)
    _, dist = station.first_hit(np.broadcast_to(np.asarray(position, dtype=np.float64), d.shape), d)
    dist = dist.reshape(len(rotations), len(local))
    lo, hi = VIEW_RANGE_M
    g, centre = dist[:, :-1], dist[:, -1]
    hit = np.isfinite(g)
    n_hit = hit.sum(axis=1)
    in_range = ((g >= lo) & (g <= hi)).sum(axis=1) / np.maximum(n_hit, 1)
    return [ViewQuality(float(centre[k]), float(n_hit[k] / g.shape[1]), float(in_range[k]),
                        float((g[k] < lo).mean())) for k in range(len(rotations))]


def view_quality(station: RayScene, position, rotation, grid: tuple[int, int] = QUALITY_GRID,
                 lens: CameraModel = DEFAULT_CAMERA, size: tuple[int, int] | None = None) -> ViewQuality:
    """Ray-cast summary of one camera's view through `lens` (see `ViewQuality`, `image_grid`)."""
    return _qualities(station, position, np.asarray(rotation, dtype=np.float64)[None], grid, lens, size)[0]


def best_view(station: RayScene, position, lens: CameraModel = DEFAULT_CAMERA, size: tuple[int, int] | None = None
              ) -> tuple[ViewQuality, np.ndarray, float] | None:
    """The best qualifying look direction from `position` (Z-up camera): (its quality, rotation,
    robust score), or None if none qualifies. The robust score averages `ViewQuality.value` over
    the view, the view panned and tilted by one perturbation sigma (+-0.2 rad), and the camera moved
    by one sigma (1 m) forward and to either side, so a pose whose perturbed cameras still see
    structure at a distance wins over one that only works when placed and aimed exactly. `lens`, `size`:
    the camera the views are scored with (`image_grid`)."""
    p = np.asarray(position, dtype=np.float64)
    rots = np.array([look_at(p, p + d) for d in fibonacci_sphere(_N_DIRECTIONS)])
    coarse = np.array([q.score for q in _qualities(station, p, rots, _SCREEN_GRID, lens, size)])
    top = [int(k) for k in np.argsort(-coarse, kind="stable")[:_REFINE] if coarse[k] > 0]
    fine = _qualities(station, p, rots[top], QUALITY_GRID, lens, size) if top else []
    top = [(k, q) for k, q in zip(top, fine) if q.ok]
    if not top:
        return None
    a = ANGLE_SIGMA_RAD
    turns = np.array([rot_y(a), rot_y(-a), rot_x(a), rot_x(-a)])
    tilted = _qualities(station, p, fm.matmul(rots[[k for k, _ in top]][:, None], turns[None]).reshape(-1, 3, 3),
                        _SCREEN_GRID, lens, size)
    robust = []
    for i, (k, q) in enumerate(top):
        r = rots[k]
        moved = [_qualities(station, p + POSITION_SIGMA_M * step, r[None], _SCREEN_GRID, lens, size)[0]
                 for step in (-r[:, 2], r[:, 0], -r[:, 0])]
        views = [q, *tilted[4 * i:4 * i + 4], *moved]
        robust.append(sum(v.value for v in views) / len(views))
    i = max(range(len(top)), key=lambda j: (robust[j], -j))
    return top[i][1], rots[top[i][0]].copy(), float(robust[i])


def _spaced(order, dist: np.ndarray, spacing: float, allowed=None) -> list[int]:
    """Greedy: walk `order`, keep an index when it is `spacing` from every kept one (and allowed)."""
    kept: list[int] = []
    for i in order:
        if (allowed is None or allowed[i]) and (not kept or dist[i, kept].min() >= spacing):
            kept.append(i)
    return kept


def base_poses(fixtures: np.ndarray, station_points: np.ndarray, station_triangles: np.ndarray,
               lens: CameraModel = DEFAULT_CAMERA, size: tuple[int, int] | None = None) -> list[CameraPose]:
    """50 deterministic poses from candidate camera positions `fixtures` (see the module doc):
    poses 1-40 train, 41-50 test, views scored through `lens` (`best_view`); raises PlacementError when
    the candidates cannot give 50."""
    pos = check_finite("fixture points", fixtures)
    station = RayScene([(station_points, station_triangles, 1)])
    views = [None if too_close(station, p, 0.5) else best_view(station, p, lens, size) for p in pos]
    order = sorted((i for i, v in enumerate(views) if v is not None), key=lambda i: (-views[i][2], i))
    if len(order) < N_TRAIN + N_TEST:
        raise PlacementError(f"only {len(order)} of {len(pos)} candidate camera positions see station "
                             f"structure {VIEW_RANGE_M[0]:.0f}-{VIEW_RANGE_M[1]:.0f} m away; 50 are needed: give "
                             "more fixture points (rig.fixtures_from_mesh(count=...)) or check the model's units")
    dist = np.sqrt(np.square(pos[:, None, :] - pos[None, :, :]).sum(axis=2))
    ahead = np.array([-views[i][1][:, 2] if views[i] is not None else np.zeros(3) for i in range(len(pos))])
    turned = fm.matmul(ahead, ahead.T) < fm.cos(fm.radians(TEST_TURN_DEG))   # views at least TEST_TURN_DEG apart

    def train_pool(test: list[int]) -> list[int]:
        if not test:
            return _spaced(order, dist, MIN_SPACING_M)
        d, t = dist[:, test], turned[:, test]
        allowed = ((d >= TEST_SEPARATION_M) & ((d >= TEST_NEIGHBOUR_M) | t)).all(axis=1)
        return _spaced(order, dist, MIN_SPACING_M, allowed)

    test: list[int] = []
    for i in order:
        if len(test) == N_TEST:
            break
        if test and dist[i, test].min() < MIN_SPACING_M:
            continue
        if len(train_pool(test + [i])) >= N_TRAIN:
            test.append(i)
    train = train_pool(test)[:N_TRAIN]
    if len(test) < N_TEST or len(train) < N_TRAIN:
        raise PlacementError(f"could not choose {N_TRAIN} training and {N_TEST} test positions "
                             f"{MIN_SPACING_M:.0f} m apart with test {TEST_SEPARATION_M:.0f} m from training "
                             f"(and {TEST_TURN_DEG:.0f} degrees turned within {TEST_NEIGHBOUR_M:.0f} m) "
                             f"({len(train)} and {len(test)} found among {len(order)} good views); give more, "
                             "more widely spread fixture points")
    return [CameraPose(k + 1, "train" if k < N_TRAIN else "test", pos[i].copy(), views[i][1].copy())
            for k, i in enumerate(train + test)]


def perturbation_matrix(angles) -> np.ndarray:
    yaw, pitch, roll = angles
    return fm.matmul(fm.matmul(rot_z(yaw), rot_y(pitch)), rot_x(roll))


_CLEARANCE_DIRS = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1],
                            [1, 1, 1], [-1, -1, 1], [1, -1, -1], [-1, 1, -1]], dtype=np.float64)
_CLEARANCE_DIRS /= fm.norm(_CLEARANCE_DIRS, axis=1, keepdims=True)   # once: every camera sample probes these
_CLEARANCE_FAN = RayFan.of_rows(_CLEARANCE_DIRS)   # and their unit vectors and float32 copy (first_hit_fan)


def too_close(scene: RayScene, p: np.ndarray, clearance: float = CLEARANCE_M) -> bool:
    """True if p is within `clearance` of the station or enclosed by it (parity vote)."""
    owner, dist = scene.first_hit_fan(p, _CLEARANCE_FAN)   # first_hit from p, bit for bit
    return bool((dist < clearance).any() or scene.inside(p))


def perturb(pose: CameraPose, rng: np.random.Generator, station: RayScene | None = None,
            max_attempts: int = 100, position_sigma_m: float = POSITION_SIGMA_M,
            angle_sigma_rad: float = ANGLE_SIGMA_RAD):
    """Paper perturbation (N(0, 1 m) per axis, N(0, 0.2 rad) per angle; a plan may set the sigmas,
    plan.model.Poses), resampled while the camera would sit inside or against the station. Returns
    (position, rotation, dpos, dang, attempts). The draws are the same for any sigmas (scaled), so
    sigma 0 gives exactly the base pose."""
    for attempt in range(1, max_attempts + 1):
        dpos = rng.normal(0.0, position_sigma_m, 3)
        dang = rng.normal(0.0, angle_sigma_rad, 3)
        pos = pose.position + dpos
        if station is None or not too_close(station, pos):
            return pos, fm.matmul(pose.rotation, perturbation_matrix(dang)), dpos, dang, attempt
    raise PlacementError(f"pose {pose.index}: no perturbed camera outside the station in {max_attempts} "
                         "attempts; move the base pose further from the structure")


def fixtures_from_mesh(points: np.ndarray, triangles: np.ndarray, count: int = 40,
                       standoff: tuple[float, float] = (1.0, 2.5), seed: int = RIG_SEED,
                       weight: str = "area") -> np.ndarray:
    """Camera fixture points for any station mesh (e.g. an imported model): surface samples pushed
    out along their face normal, kept only if clear of all structure. `weight`: "area" samples the
    surface uniformly; "triangle" picks every triangle equally often, which favours detailed
    structure (modules, truss, fixtures) over large plain panels (solar wings, radiators)."""
    if weight not in ("area", "triangle"):
        raise ValueError(f"weight must be 'area' or 'triangle', got {weight!r}")
    p = np.asarray(points, dtype=np.float64)
    t = np.asarray(triangles)
    n = np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])
    area = fm.norm(n, axis=1)
    keep = np.flatnonzero(area > 0)
    prob = area[keep] / area[keep].sum() if weight == "area" else None
    rng = np.random.default_rng(seed)
    scene = RayScene([(p, t, 1)])
    centre = 0.5 * (p.min(axis=0) + p.max(axis=0))
    out = []
    for _ in range(count * 20):
        i = rng.choice(keep, p=prob)
        a, b = rng.random(2)
        if a + b > 1:
            a, b = 1 - a, 1 - b
        q = p[t[i, 0]] + a * (p[t[i, 1]] - p[t[i, 0]]) + b * (p[t[i, 2]] - p[t[i, 0]])
        normal = n[i] / area[i]
        if fm.dot(normal, q - centre) < 0:  # meshes of unknown winding: point away from the centre
            normal = -normal
        f = q + normal * rng.uniform(*standoff)
        if not too_close(scene, f, clearance=0.5):
            out.append(f)
        if len(out) == count:
            break
    if len(out) < 10:
        raise PlacementError(f"found only {len(out)} clear camera fixtures on the station mesh; "
                             "is it closed and in metres?")
    return np.array(out)
