"""Coverage: which floor a survey's sweeps reach, and the least-energy loop that reaches a target share of it.

The model (pure functions). The vehicle flies the loop as the ideal plant does (legs at speed, turns in place
at the yaw-rate limit, `sitl.vehicle.ideal_plant`), the servo sweeps its waveform (eqs. 1-2) at the
rangefinder's sample rate, and each beam is cast at the floor of the empty building: it counts when it meets
the floor inside the walls (a beam whose floor point lies beyond a wall met the wall first) within the
certain-echo reach at its incidence (`range_check.RangeLimit`). A floor cell is *covered* when it lies both
inside the convex hull of the floor hits (where the report's surface exists: its R_a, eq. 9, is the share of
cells the triangulation of the points covers) and within `seen_radius_m` of a hit (so a hull spanned by a few
far-apart fan lines is not counted as seen). Predicted R_a = covered cells / floor cells. A pile only brings
surfaces nearer and shadows floor behind it, so the flat floor is the model's default case; with an earlier
survey's surface (`CoverageTarget.surface`, `surveyed_surface`) the beams stop at the first surface they meet.

The plan family (`LoopPlan`): a closed loop around the building with one offset per wall (four, not the
paper's single P_traj), optionally with every corner cut by a short 45-degree leg. That leg's sweep plane
is square to the building's diagonal, so its fans point into the corner the plain turn leaves between two or
three fan lines. Speed is searched too. Extra interior legs (a lawnmower) are not in this increment: with a
rangefinder whose floor reach does not span half the building the planner refuses the target instead.

The energy (`EnergyModel`): the JSBSim F450 draws a near-constant power at survey speeds (the reproduction's
energy follows flight time to within 1 %: docs/results.md), so E = P L / v + e_turn sum|turn| with P and
e_turn fitted from two JSBSim flights of the rectangle (docs/coverage.md gives the fit and checks it).

The planner (`plan_coverage`): for each speed and corner mode, start from the loop nearest the walls and
move one wall's leg inwards at a time, taking the move that saves the most energy while the predicted
coverage stays at the target, until no move does; the cheapest of these plans wins. It refuses (ValueError,
one line) a target no plan in the family reaches.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from statistics import NormalDist

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from firmware_py.core.config_file import MIN_YAW_RATE_DEG_S
from firmware_py.core.frames import StorageFrame
from firmware_py.core.sensor import RangefinderSpec
from firmware_py.core.storage import Storage
from firmware_py.core.surface_file import SEEN_RADIUS_M
from firmware_py.core.waveform import Waveform
from sitl.missions.range_check import RangeLimit
from sitl.missions.surveyed_surface import HeightField, first_hits_w

COVERAGE_CELL_M = 0.25
"""The floor cell: the ground report's default grid (ground.surface.DEFAULT_CELL_M), so R_a compares cell for cell."""
DEFAULT_SEEN_RADIUS_M = SEEN_RADIUS_M
"""A cell counts as seen when a floor hit lies this near (an option; `firmware_py.core.surface_file.SEEN_RADIUS_M`
says why this default, which the report's bridged area takes too)."""
WALLS = ("south (y = 0)", "east (x = L)", "north (y = W)", "west (x = 0)")
OFFSET_STEPS = tuple(round(0.05 * k, 2) for k in range(1, 9))
"""Each wall's offset as a share of the building's size across it: 5 % (the paper's nearest) to 40 %."""
NEAR_WALL_STEPS = (0.0125, 0.025, 0.0375)
"""Offsets nearer than the paper's 5 %, each searched where it keeps the clearance plus the vehicle's
overshoot at the plan's speed (`EnergyModel.overshoot_m`) from the wall: legs near a wall see its foot with
beams steep enough for the report's wall band (`WallBand`)."""
SPEEDS_M_S = (0.5, 1.0, 1.5, 2.0)
"""The speeds searched (the paper flew 0.5, 1 and 2 m/s)."""


@dataclass(frozen=True)
class EnergyModel:
    """Flight time and energy of a mission of straight legs on the JSBSim F450 (`tools.energy_fit` fits it).

    The vehicle draws a near-constant power (E = P T), so the model is one of flight time:
    T = a L / v + b sum min(|dpsi|, 90 deg) / omega + b' sum max(|dpsi| - 90 deg, 0) / omega
        + c v sum min(|dpsi| / 90 deg, 1) + d n.
    The legs at speed (a ~ 1); the turns at the yaw-rate limit, the vehicle moving off along the new leg
    through the last 90 degrees of a turn (b < 1: eq. 15 scales the speed by cos of the heading error);
    braking and accelerating again at every waypoint, in proportion to the speed and to how much of it the
    turn takes away (a 90-degree turn stops the vehicle); a settling time d per waypoint. Fitted on loops,
    lawnmower and sawtooth tours and out-and-back legs at 0.5-2 m/s and 30 deg/s, checked on flights not in
    the fit (docs/coverage.md); at yaw rates far below 30 deg/s the turn terms do not hold (at 1 deg/s the
    autopilot creeps towards the next waypoint while it turns: 35 % more than the model)."""

    power_w: float = 145.38
    leg_factor: float = 0.972
    turn_factor: float = 0.565
    reverse_factor: float = 0.717
    stop_s_per_m_s: float = 0.585
    waypoint_s: float = 0.929
    brake_m_s2: float = 3.13
    """What the vehicle overshoots a 90-degree corner by, v^2 / (2 brake): the least braking the fit's
    flights showed (`tools.energy_fit`); the planner keeps that much more than the clearance from a wall."""

    def flight_time_s(self, path_m: float, speed_m_s: float, turns_rad, yaw_rate_rad_s: float) -> float:
        """turns_rad: the heading change at every waypoint flown (the closing one included)."""
        t = np.abs(np.asarray(turns_rad, dtype=float))
        stops = np.minimum(t / (np.pi / 2), 1.0).sum()
        return float(self.leg_factor * path_m / speed_m_s
                     + self.turn_factor * np.minimum(t, np.pi / 2).sum() / yaw_rate_rad_s
                     + self.reverse_factor * np.maximum(t - np.pi / 2, 0.0).sum() / yaw_rate_rad_s
                     + self.stop_s_per_m_s * speed_m_s * stops + self.waypoint_s * len(t))

    def energy_j(self, path_m: float, speed_m_s: float, turns_rad, yaw_rate_rad_s: float) -> float:
        return self.power_w * self.flight_time_s(path_m, speed_m_s, turns_rad, yaw_rate_rad_s)

    def overshoot_m(self, speed_m_s: float) -> float:
        """How far past a square corner's waypoint the vehicle runs before it stops."""
        return speed_m_s ** 2 / (2 * self.brake_m_s2)


def loop_turns_rad(waypoints_w: np.ndarray) -> np.ndarray:
    """The heading change at every waypoint of a closed loop, the first from the closing leg (as flown)."""
    d = np.diff(np.asarray(waypoints_w, dtype=float), axis=0)
    course = np.arctan2(d[:, 1], d[:, 0])
    return np.abs((np.diff(np.r_[course[-1], course]) + np.pi) % (2 * np.pi) - np.pi)


def loop_turned_rad(waypoints_w: np.ndarray) -> float:
    """The yaw a closed loop turns: at every waypoint, the first from the closing leg (as the ideal plant flies)."""
    return float(loop_turns_rad(waypoints_w).sum())


def mission_energy_j(mission, model: EnergyModel | None = None) -> float:
    """The energy model's figure for any loop mission (a rectangle or a `LoopMission`)."""
    return (model or EnergyModel()).energy_j(mission.path_length_m(), mission.speed_m_s,
                                             loop_turns_rad(mission.waypoints_w()), mission.yaw_rate_max_rad_s)


def mission_time_s(mission, model: EnergyModel | None = None) -> float:
    """The energy model's flight time for any loop mission."""
    return (model or EnergyModel()).flight_time_s(mission.path_length_m(), mission.speed_m_s,
                                                  loop_turns_rad(mission.waypoints_w()), mission.yaw_rate_max_rad_s)


@dataclass(frozen=True)
class LoopMission:
    """A closed loop of waypoints flown like `rectangle.Mission` (the same attributes the plants, the plan
    export and the flight runners read): the coverage planner's and the gap re-flight's mission (`gaps`; two
    distinct waypoints: out and back)."""

    storage: Storage = field(default_factory=Storage)
    waypoints: tuple[tuple[float, float], ...] = ()
    speed_m_s: float = 1.0
    altitude_m: float = 12.0
    yaw_rate_max_rad_s: float = math.radians(30.0)
    min_clearance_m: float = 0.5
    plan: dict = field(default_factory=dict, hash=False)  # what the planner chose and predicted (in the header)

    def __post_init__(self) -> None:
        s = self.storage
        wp = np.asarray(self.waypoints, dtype=float)
        if wp.ndim != 2 or wp.shape[1] != 2 or len(wp) < 3 or not np.all(np.isfinite(wp)):
            raise ValueError("a loop needs at least 2 finite waypoints (x, y) and the first again at the end")
        if not np.allclose(wp[0], wp[-1]):
            raise ValueError("the loop must end where it starts (first waypoint == last)")
        c = self.min_clearance_m
        if wp[:, 0].min() < c or wp[:, 0].max() > s.length_m - c or wp[:, 1].min() < c \
                or wp[:, 1].max() > s.width_m - c:
            raise ValueError(f"a waypoint lies within {c:g} m of a wall of the {s} building")
        if np.any(np.linalg.norm(np.diff(wp, axis=0), axis=1) < 1e-6):
            raise ValueError("two consecutive waypoints coincide")
        if not (math.isfinite(self.speed_m_s) and 0.05 <= self.speed_m_s <= 15.0):
            raise ValueError(f"speed must be 0.05-15 m/s, got {self.speed_m_s}")
        if not (math.isfinite(self.yaw_rate_max_rad_s)
                and math.radians(MIN_YAW_RATE_DEG_S) <= self.yaw_rate_max_rad_s <= 2 * math.pi):
            raise ValueError(f"max yaw rate must be in [{MIN_YAW_RATE_DEG_S:g}, 360] deg/s, "
                             f"got {math.degrees(self.yaw_rate_max_rad_s):g}")
        if not (math.isfinite(self.altitude_m) and c < self.altitude_m <= s.height_m - c):
            raise ValueError(f"altitude {self.altitude_m:g} m does not fit the {s} building "
                             f"(needs {c:g} m clearance to floor and roof)")

    def waypoints_w(self) -> np.ndarray:
        return np.asarray(self.waypoints, dtype=float)

    def path_length_m(self) -> float:
        return float(np.linalg.norm(np.diff(self.waypoints_w(), axis=0), axis=1).sum())

    def turned_rad(self) -> float:
        return loop_turned_rad(self.waypoints_w())

    def to_dict(self) -> dict:
        return {"kind": "coverage", "storage": self.storage.to_dict(), "waypoints": [list(p) for p in self.waypoints],
                "speed_m_s": self.speed_m_s, "altitude_m": self.altitude_m,
                "yaw_rate_max_rad_s": self.yaw_rate_max_rad_s, "min_clearance_m": self.min_clearance_m,
                "plan": self.plan}

    @property
    def mission_id(self) -> str:
        blob = json.dumps(self.to_dict(), sort_keys=True).encode()
        return hashlib.sha256(blob).hexdigest()[:12]


@dataclass(frozen=True)
class LoopPlan:
    """A member of the plan family: offsets from the walls (m; south, east, north, west: `WALLS`), the corner
    cut (m; 0: plain 90-degree turns) and the speed."""

    offsets_m: tuple[float, float, float, float]
    corner_cut_m: float = 0.0
    speed_m_s: float = 1.0

    def waypoints_w(self, storage: Storage) -> np.ndarray:
        """The loop counter-clockwise from the south-west corner, first == last."""
        s, e, n, w = self.offsets_m
        c = np.array([[w, s], [storage.length_m - e, s], [storage.length_m - e, storage.width_m - n],
                      [w, storage.width_m - n]])
        legs = np.linalg.norm(np.diff(np.vstack([c, c[:1]]), axis=0), axis=1)
        if legs.min() <= 0 or 2 * self.corner_cut_m >= legs.min():
            raise ValueError(f"offsets {self.offsets_m} and corner cut {self.corner_cut_m:g} m leave no loop in the "
                             f"{storage} building")
        if self.corner_cut_m <= 0:
            return np.vstack([c, c[:1]])
        pts = []
        for i in range(4):
            u_in = c[i] - c[i - 1]
            u_out = c[(i + 1) % 4] - c[i]
            pts += [c[i] - self.corner_cut_m * u_in / np.linalg.norm(u_in),
                    c[i] + self.corner_cut_m * u_out / np.linalg.norm(u_out)]
        return np.vstack([pts, pts[:1]])

    def mission(self, storage: Storage, altitude_m: float, yaw_rate_max_rad_s: float, min_clearance_m: float = 0.5,
                plan: dict | None = None) -> LoopMission:
        wp = self.waypoints_w(storage)
        return LoopMission(storage, tuple((float(x), float(y)) for x, y in wp), self.speed_m_s, altitude_m,
                           yaw_rate_max_rad_s, min_clearance_m, dict(plan or {}))


@dataclass(frozen=True)
class Coverage:
    """What the model predicts for a loop (module docstring)."""

    predicted_ra_pct: float  # covered cells / floor cells
    hull_pct: float  # inside the floor hits' convex hull (the report's surface extent)
    seen_pct: float  # within the seen radius of a hit
    n_hits: int
    covered: np.ndarray  # (nx, ny) bool


@dataclass(frozen=True)
class WallBand:
    """The band along each wall in which the ground station takes a point for the wall
    (`ground.pointcloud.structure_mask`, `plane_tolerances_m`): k sigma_r(r) |d . n| + half the range
    resolution + k position sigmas + 1 mm, k from the survey's size (`structure_n_sigma`). A floor point in it
    is kept (it lies nearer the floor than the wall); material leaning on a wall is not, so where a pile meets
    a wall the report's surface ends the band's width short of it, and its R_a loses the cells between. The
    band widens with the beam's slant towards the wall: a leg far from a wall loses its row of cells.

    The planner cannot know where material will lean on the walls, so it plans for it at every wall (the
    floor hits in the band do not count, `floor_hits_w`); on an earlier survey's surface the rule is the
    report's own (the band's hits count where they lie nearer the floor than the wall)."""

    range_sigma_m: float
    range_sigma_rel: float
    resolution_m: float
    position_sigma_m: float = 0.0

    @classmethod
    def of(cls, spec: RangefinderSpec, position_sigma_m: float = 0.0) -> WallBand:
        """The band the report will use for this rangefinder (its log header states the spec's sigmas)."""
        return cls(spec.range_sigma_m, spec.range_sigma_rel, spec.resolution_m, position_sigma_m)

    def tolerances_m(self, range_m: np.ndarray, dirs_w: np.ndarray, n_points: int) -> np.ndarray:
        """(N, 3) each point's tolerance along x, y and z (ground.pointcloud.plane_tolerances_m)."""
        k = structure_n_sigma(n_points)
        along = k * np.maximum(self.range_sigma_m, self.range_sigma_rel * np.asarray(range_m)) \
            + 0.5 * self.resolution_m
        return along[:, None] * np.abs(dirs_w) + (k * self.position_sigma_m + 1e-3)


def structure_n_sigma(n_points: int, escapes: float = 0.01) -> float:
    """ground.pointcloud.structure_n_sigma (the simulator does not import the ground station): the smallest
    k >= 3 at which n_points normal errors leave on average at most `escapes` points beyond k sigma."""
    if n_points <= 0:
        return 3.0
    return max(3.0, -NormalDist().inv_cdf(min(0.5, escapes / n_points)))


def in_wall_band(points_w: np.ndarray, tol_m: np.ndarray, storage: Storage, material_everywhere: bool) -> np.ndarray:
    """True for points the report would take for a wall: within their tolerance of one and, unless
    material_everywhere (the planner's assumption on a bare floor), not nearer the floor (structure_mask)."""
    p = np.asarray(points_w, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        to_wall = np.minimum.reduce([p[:, 0] / tol_m[:, 0], (storage.length_m - p[:, 0]) / tol_m[:, 0],
                                     p[:, 1] / tol_m[:, 1], (storage.width_m - p[:, 1]) / tol_m[:, 1]])
        if material_everywhere:
            return to_wall <= 1.0
        to_floor = np.abs(p[:, 2]) / tol_m[:, 2]
    return (to_wall <= 1.0) & ~(to_floor < to_wall)


def floor_hits_w(mission, waveform: Waveform, limit: RangeLimit, rate_hz: float,
                 lever_arm_body_m: tuple[float, float, float] = (0.0, 0.0, 0.10),
                 surface: HeightField | None = None, walls: WallBand | None = None) -> np.ndarray:
    """(N, 2) floor positions (W) of the beams that meet the empty building's floor within reach, or with an
    earlier survey's `surface` the first surface each beam meets (a pile's flank hides the floor behind it).
    With `walls`, the hits the report would take for a wall are left out (`WallBand`)."""
    from sitl.vehicle.ideal_plant import IdealPlant
    frame = StorageFrame()
    plant = IdealPlant(mission, frame)
    t = plant.sample_times(rate_hz)
    traj = plant.states(t)
    # The ideal plant flies level: the body's forward and right axes are the heading's, so the beam
    # d_B = [0, sin g, cos g] (frames.beam_dir_body, square mounting) and the lever arm turn by the yaw alone.
    # With the identity frame, W = (north, -east, up).
    psi, g = traj.yaw_rad, np.asarray(waveform.angle(t), dtype=float)
    fwd = np.column_stack([np.cos(psi), -np.sin(psi)])
    right = np.column_stack([-np.sin(psi), -np.cos(psi)])
    lx, ly, lz = (float(v) for v in lever_arm_body_m)
    pos = traj.pos_ned_m
    o = np.column_stack([pos[:, 0], -pos[:, 1]]) + lx * fwd + ly * right
    o = np.column_stack([o, -pos[:, 2] - lz])
    d = np.column_stack([np.sin(g)[:, None] * right, -np.cos(g)])
    down = d[:, 2] < -1e-9
    o, d = o[down], d[down]
    n_samples = len(t)
    if surface is not None:
        hits, r = first_hits_w(o, d, surface, 0.5 * COVERAGE_CELL_M)
        ok = np.isfinite(r)
        ok[ok] = r[ok] <= limit.reach_m(-d[ok, 2]) * (1 + 1e-9)
        if walls is not None:
            ok[ok] = ~in_wall_band(hits[ok], walls.tolerances_m(r[ok], d[ok], n_samples), mission.storage, False)
        return hits[ok, :2]
    r = -o[:, 2] / d[:, 2]
    p = o[:, :2] + r[:, None] * d[:, :2]
    s = mission.storage
    ok = (p[:, 0] >= 0) & (p[:, 0] <= s.length_m) & (p[:, 1] >= 0) & (p[:, 1] <= s.width_m)
    ok &= r <= limit.reach_m(-d[:, 2]) * (1 + 1e-9)
    if walls is not None:
        ok[ok] = ~in_wall_band(np.column_stack([p[ok], np.zeros(int(ok.sum()))]),
                               walls.tolerances_m(r[ok], d[ok], n_samples), s, True)
    return p[ok]


def within_reach(points_xy: np.ndarray, shape: tuple[int, int], length_m: float, width_m: float, cell_m: float,
                 radius_m: float) -> np.ndarray:
    """(nx, ny) the cells of the grid over [0, L] x [0, W] within radius_m of a point: the distance from each cell to
    the nearest cell holding one (cells of side cell_m). The coverage model's "seen" (module docstring), and the gap
    re-flight's test of the cells a report's hull bridged (`sitl.missions.gaps`)."""
    nx, ny = shape
    hit = np.zeros((nx, ny), dtype=bool)
    if len(points_xy):
        ix = np.clip((points_xy[:, 0] / length_m * nx).astype(int), 0, nx - 1)
        iy = np.clip((points_xy[:, 1] / width_m * ny).astype(int), 0, ny - 1)
        hit[ix, iy] = True
    if not hit.any():
        return hit
    from scipy import ndimage  # here, not at the top: importing it costs every `pilescan-sitl` start 0.24 s
    return ndimage.distance_transform_edt(~hit) * cell_m <= radius_m


def coverage_of_hits(hits_w: np.ndarray, storage: Storage, seen_radius_m: float = DEFAULT_SEEN_RADIUS_M,
                     cell_m: float = COVERAGE_CELL_M, hull_points_w: np.ndarray | None = None) -> Coverage:
    """The floor cells the hits cover (module docstring). hull_points_w (M, 2), optional: points an earlier
    flight measured, merged with these hits into one cloud: they widen the hull (the merged report's surface)
    but are not new sightings (the seen radius counts the hits only)."""
    nx, ny = max(1, round(storage.length_m / cell_m)), max(1, round(storage.width_m / cell_m))
    cx = (np.arange(nx) + 0.5) * storage.length_m / nx
    cy = (np.arange(ny) + 0.5) * storage.width_m / ny
    extra = np.empty((0, 2)) if hull_points_w is None else np.asarray(hull_points_w, dtype=float).reshape(-1, 2)
    if len(hits_w) == 0 or len(hits_w) + len(extra) < 3:
        z = np.zeros((nx, ny), dtype=bool)
        return Coverage(0.0, 0.0, 0.0, len(hits_w), z)
    seen = within_reach(hits_w, (nx, ny), storage.length_m, storage.width_m, cell_m, seen_radius_m)
    gx, gy = np.meshgrid(cx, cy, indexing="ij")
    try:
        eq = ConvexHull(np.vstack([hits_w, extra])).equations  # a x + b y + c <= 0 inside every facet
        inside = np.all(eq[:, 0, None, None] * gx + eq[:, 1, None, None] * gy + eq[:, 2, None, None] <= 1e-9, axis=0)
    except QhullError:  # all hits on a line: no surface
        inside = np.zeros((nx, ny), dtype=bool)
    covered = inside & seen
    return Coverage(100.0 * covered.mean(), 100.0 * inside.mean(), 100.0 * seen.mean(), len(hits_w), covered)


def predict_coverage(mission, waveform: Waveform, limit: RangeLimit, rate_hz: float,
                     lever_arm_body_m: tuple[float, float, float] = (0.0, 0.0, 0.10),
                     seen_radius_m: float = DEFAULT_SEEN_RADIUS_M, surface: HeightField | None = None,
                     walls: WallBand | None = None) -> Coverage:
    """The model's predicted coverage of a mission (a `rectangle.Mission` or a `LoopMission`); with `walls`,
    for material that may lean on any wall (`WallBand`)."""
    return coverage_of_hits(floor_hits_w(mission, waveform, limit, rate_hz, lever_arm_body_m, surface, walls),
                            mission.storage, seen_radius_m)


@dataclass(frozen=True)
class CoverageTarget:
    """What the planner must reach and with what: the target predicted R_a and the payload's sweep."""

    coverage_pct: float
    waveform: Waveform
    limit: RangeLimit
    rate_hz: float
    lever_arm_body_m: tuple[float, float, float] = (0.0, 0.0, 0.10)
    seen_radius_m: float = DEFAULT_SEEN_RADIUS_M
    speeds_m_s: tuple[float, ...] = SPEEDS_M_S
    energy: EnergyModel = field(default_factory=EnergyModel)
    also_waveforms: tuple[Waveform, ...] = ()
    """Other servo start positions the plan must reach the target at too: the plan's predicted coverage is
    the worst over `waveform` and these (a plan flown whatever position the servo starts in)."""
    surface: HeightField | None = field(default=None, hash=False, compare=False)
    """An earlier survey's surface to cast the beams at (`surveyed_surface`); None: the empty floor."""
    walls: WallBand | None = None
    """The report's wall band (`WallBand.of(spec)`): plan for material leaning on the walls; None: count the
    floor up to the walls (bare walls' foot, the first increment's model)."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.coverage_pct) and 0 < self.coverage_pct <= 100):
            raise ValueError(f"target coverage must be in (0, 100] %, got {self.coverage_pct:g}")
        if not (math.isfinite(self.seen_radius_m) and self.seen_radius_m > 0):
            raise ValueError(f"seen radius must be > 0 m, got {self.seen_radius_m:g}")


@dataclass(frozen=True)
class PlannedLoop:
    """The planner's choice: the plan, its mission, its predicted coverage and energy, how many plans it tried."""

    plan: LoopPlan
    mission: LoopMission
    coverage: Coverage
    energy_j: float
    n_evaluated: int


def worst_coverage(mission, target: CoverageTarget) -> Coverage:
    """The predicted coverage at the target's worst servo start position (`waveform`, then `also_waveforms`);
    stops at the first position below the target (the plan fails it whatever the others give)."""
    worst = None
    for wf in (target.waveform, *target.also_waveforms):
        cov = predict_coverage(mission, wf, target.limit, target.rate_hz, target.lever_arm_body_m,
                               target.seen_radius_m, target.surface, target.walls)
        if worst is None or cov.predicted_ra_pct < worst.predicted_ra_pct:
            worst = cov
        if worst.predicted_ra_pct < target.coverage_pct:
            break
    return worst


def plan_coverage(storage: Storage, target: CoverageTarget, altitude_m: float = 12.0,
                  yaw_rate_max_rad_s: float = math.radians(30.0), min_clearance_m: float = 0.5,
                  progress: Callable[[int, float], None] | None = None) -> PlannedLoop:
    """The least-energy loop of the family whose predicted coverage reaches the target (module docstring);
    ValueError (one line) when none does. progress(loops evaluated, best predicted coverage so far, %) is called
    after each loop evaluated: on an earlier survey's surface, for every servo start position, a plan takes
    minutes."""
    if not (math.isfinite(altitude_m) and min_clearance_m < altitude_m <= storage.height_m - min_clearance_m):
        raise ValueError(f"altitude {altitude_m:g} m does not fit the {storage} building "
                         f"(needs {min_clearance_m:g} m clearance to floor and roof)")
    h = altitude_m - float(target.lever_arm_body_m[2])
    reach = target.limit.floor_reach_m(h)
    if reach <= 0:
        raise ValueError(f"the rangefinder reaches no floor from {h:.1f} m above it "
                         f"(planning range {target.limit.describe()}): fly lower")
    if 2 * reach < min(storage.length_m, storage.width_m) * (1 - 2 * OFFSET_STEPS[0]):
        raise ValueError(f"the floor reach ({reach:.1f} m either side of the track) does not span half of the "
                         f"{storage} building: a loop cannot cover it and interior legs (a lawnmower) are not "
                         "planned yet; fly lower or survey a narrower bay")
    sizes = (storage.width_m, storage.length_m, storage.width_m, storage.length_m)  # across each wall
    cache: dict[LoopPlan, tuple[Coverage, float] | None] = {}
    most = 0.0  # the best predicted coverage of any loop evaluated, for progress

    def evaluate(plan: LoopPlan) -> tuple[Coverage, float] | None:
        nonlocal most
        if plan not in cache:
            try:
                m = plan.mission(storage, altitude_m, yaw_rate_max_rad_s, min_clearance_m)
            except ValueError:
                cache[plan] = None
                return None
            cov = worst_coverage(m, target)
            cache[plan] = cov, mission_energy_j(m, target.energy)
            most = max(most, cov.predicted_ra_pct)
            if progress is not None:
                progress(len(cache), most)
        return cache[plan]

    def ladder(size_m: float, speed: float) -> tuple[float, ...]:
        """A wall's offsets (m), nearest first: the near-wall steps the vehicle can fly, then the family's that keep
        the clearance (in a small building the family's first steps lie within it: 5 % of 8 m is 0.4 m)."""
        near = min_clearance_m + target.energy.overshoot_m(speed)
        return (tuple(f * size_m for f in NEAR_WALL_STEPS if f * size_m >= near)
                + tuple(f * size_m for f in OFFSET_STEPS if f * size_m >= min_clearance_m))

    ladders = {v: [ladder(z, v) for z in sizes] for v in target.speeds_m_s}
    if any(not rungs for per_wall in ladders.values() for rungs in per_wall):
        raise ValueError(f"no loop fits the {storage} building {min_clearance_m:g} m from its walls")

    def plan_of(steps: tuple[int, ...], cut_m: float, speed: float) -> LoopPlan:
        return LoopPlan(tuple(ladders[speed][i][k] for i, k in enumerate(steps)), cut_m, speed)

    best: tuple[float, LoopPlan, Coverage] | None = None
    best_reached: float | None = None  # the best predicted coverage of the loops nearest the walls that could be flown
    cut = max(min_clearance_m, 0.05 * min(storage.length_m, storage.width_m))
    for speed in target.speeds_m_s:
        for cut_m in (0.0, cut):
            steps = (0, 0, 0, 0)
            got = evaluate(plan_of(steps, cut_m, speed))
            if got is None:
                continue
            best_reached = max(best_reached or 0.0, got[0].predicted_ra_pct)
            if got[0].predicted_ra_pct < target.coverage_pct:
                continue
            while True:  # move one wall's leg inwards: the cheapest move that keeps the target
                moves = []
                for i in range(4):
                    if steps[i] + 1 >= len(ladders[speed][i]):
                        continue
                    nxt = (*steps[:i], steps[i] + 1, *steps[i + 1:])
                    r = evaluate(plan_of(nxt, cut_m, speed))
                    if r is not None and r[0].predicted_ra_pct >= target.coverage_pct:
                        moves.append((r[1], nxt))
                if not moves:
                    break
                steps = min(moves)[1]
            cov, e = evaluate(plan_of(steps, cut_m, speed))
            if best is None or e < best[0]:
                best = (e, plan_of(steps, cut_m, speed), cov)
    if best is None and best_reached is None:
        raise ValueError(f"no loop fits the {storage} building: every loop nearest its walls was refused (the "
                         f"clearance {min_clearance_m:g} m, the corner turns)")
    if best is None:
        shown = math.floor(best_reached * 100.0) / 100.0  # 99.996 % is not "100.0 %" when 100 % is not reached
        raise ValueError(f"no loop reaches {target.coverage_pct:g} % predicted coverage (best {shown:.2f} %, "
                         "legs as near every wall as the vehicle may fly); lower --coverage, sweep slower, or fly "
                         "lower")
    e, plan, cov = best
    record = {"coverage_target_pct": target.coverage_pct, "predicted_ra_pct": round(float(cov.predicted_ra_pct), 3),
              "predicted_energy_j": round(e, 1), "offsets_m": [round(v, 3) for v in plan.offsets_m],
              "walls": list(WALLS), "corner_cut_m": plan.corner_cut_m, "seen_radius_m": target.seen_radius_m,
              "servo_start_positions": 1 + len(target.also_waveforms),
              "surface": target.surface.source if target.surface is not None else None,
              "material_at_walls": target.walls is not None}
    mission = plan.mission(storage, altitude_m, yaw_rate_max_rad_s, min_clearance_m, record)
    return PlannedLoop(plan, mission, cov, e, len(cache))
