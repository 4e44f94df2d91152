"""Gap re-flights: a short mission over the floor an earlier report could not see (`plan --fill-gaps REPORT_DIR`).

What the report could not see: the cells of its surface file that were filled by its empty-cell policy, not
fitted to points (`surface.npz` version 2's `fitted` mask; for a version 1 file, the cells outside the convex
hull of its `cloud.ply`: `surveyed_surface.load_height_field`), and the cells its points' hull bridged: fitted,
but with no point of its `cloud.ply` within the seen radius (the coverage model's "seen", `coverage.within_reach`).
Why the bridged too: the hull spans a trough a pile's shoulder hides, or a corner between two fans, with long
triangles, and the surface there is a guess as much as the fill is (the paper's pile 2 from the P_traj 20 %
rectangle: most of its volume error lies in the strips along the end walls, half of it in such bridges; design
notes, "Where the remaining error lies"). Both are targets. The filled cells count as floor on the surface the
re-flight is predicted on (nothing measured stands there); the bridged keep the bridge's heights, a guess, but one
that joins seen ground (as floor, the cells between two fans a little too far apart would be pits no beam could be
predicted to reach). Unseen cells nearest the same wall and within
two seen radii of each other are one region (one leg can see them together; a band round a pile is one region
per wall, not one ring no straight leg can follow).

The mission: straight legs, each region proposing legs along x and along y (the sweep plane is square to the
track, so the fans lie across it and reach the region's cells) over its extent along the track plus the seen
radius at each end, on five tracks across it (its edges, its centre line and the quarter lines, kept the family's
5 % from the walls). The chosen legs are joined in a closed tour (nearest end next, from the start that makes it
shortest) as a `LoopMission`, which the plants, the autopilot and the QGC export fly like any loop; one leg alone
is flown out and back.

The check: the coverage model (`coverage.floor_hits_w` on the report's surface, the unseen cells as floor that
must be reached; `coverage.coverage_of_hits` with the report's measured extent widening the hull, as the merged
cloud's triangulation will) predicts which gap cells each candidate leg covers, flown alone at the fastest speed
searched (its fans farthest apart: what it covers at least). Per speed, legs are
taken greedily, the most newly covered gap cells per joule (`coverage.EnergyModel`, a turn at each end) first,
until together they cover the target share; their tour is then checked as a whole (more legs are added while it
falls short), and the least-energy tour over the speeds wins. A target none reaches is refused with the best
prediction.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from itertools import pairwise
from pathlib import Path

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from firmware_py.core.safe_read import InputError, json_object, load_json
from firmware_py.core.site import Site, site_difference
from firmware_py.core.storage import Storage
from sitl.missions.coverage import (
    OFFSET_STEPS,
    CoverageTarget,
    LoopMission,
    coverage_of_hits,
    floor_hits_w,
    mission_energy_j,
    within_reach,
)
from sitl.missions.surveyed_surface import CLOUD_FILE, HeightField, cloud_points_xy, load_height_field

REPORT_FILE = "report.json"
"""A finished report's marker (ground.report.REPORT_FILE: written last)."""
DEFAULT_GAP_TARGET_PCT = 95.0
"""The share of the gap cells the re-flight must be predicted to cover (an option)."""
TRACK_FRACTIONS = (0.0, 0.25, 0.5, 0.75, 1.0)
"""Where across a region's extent its candidate tracks lie: its edges, its centre line and between."""


@dataclass(frozen=True)
class Gaps:
    """What a report could not see, on its grid."""

    surface: HeightField  # the report's heights, its unseen cells as floor
    unseen: np.ndarray = field(compare=False)  # (nx, ny) bool
    regions: tuple[np.ndarray, ...] = field(compare=False)  # (nx, ny) bool each, the largest first
    source: str = ""
    bridged: np.ndarray | None = field(default=None, compare=False)
    """(nx, ny) bool: the unseen cells the report's hull bridged (fitted, no point within the seen radius); inside
    its R_a (eq. 9) already. None: none (no cloud to tell)."""

    @property
    def cell_m(self) -> float:
        return self.surface.length_m / self.unseen.shape[0]

    def measured_outline_w(self) -> np.ndarray:
        """(M, 2) the measured cells' corners on the hull of their extent: what widens a merged cloud's hull (the
        report's fitted cells, the bridged among them)."""
        nx, ny = self.unseen.shape
        ix, iy = np.nonzero(self.surface.measured)
        if len(ix) == 0:
            return np.empty((0, 2))
        cx, cy = self.surface.length_m / nx, self.surface.width_m / ny
        pts = np.column_stack([(ix + 0.5) * cx, (iy + 0.5) * cy])
        try:
            return pts[ConvexHull(pts).vertices]
        except (QhullError, ValueError):  # fewer than three cells, or on a line: they are their own outline
            return pts


def _site_mismatch(recorded: dict | None, site: Site | None) -> str | None:
    if recorded is None or site is None:
        return None
    try:
        return site_difference(Site.from_dict(recorded), site)
    except ValueError as exc:
        return f"its site record is malformed ({exc})"


def load_gaps(report_dir: str | Path, storage: Storage, site: Site | None = None,
              seen_radius_m: float = 1.0) -> Gaps:
    """The unseen cells of the finished report in report_dir, checked to be of this building (and site);
    ValueError (one line) for a missing, unfinished, damaged or foreign report, or one that saw everything."""
    d = Path(report_dir)
    if not d.is_dir():
        raise ValueError(f"no such report directory: {d}")
    try:
        json_object(load_json(d / REPORT_FILE, "report file"), f"report file {d / REPORT_FILE}")
    except (InputError, OSError) as exc:  # missing (a report that failed half-way), unreadable, not JSON
        why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise ValueError(f"{d} holds no finished report ({REPORT_FILE}: {why})"[:300]) from None
    surface = load_height_field(d, storage)
    if surface.measured is None:
        raise ValueError(f"{d}: its surface file does not say which cells were seen (version 1) and it has no "
                         "cloud.ply: report the run again")
    why = _site_mismatch(surface.site, site)
    if why is not None:
        raise ValueError(f"{d} is a survey of another building: {why}")
    bridged = _bridged(d / CLOUD_FILE, surface, seen_radius_m)
    unseen = ~surface.measured if bridged is None else ~surface.measured | bridged
    if not unseen.any():
        raise ValueError(f"{d}: the report saw the whole floor (no unseen cells): there are no gaps to re-fly")
    from scipy import ndimage  # here, not at the top: importing it costs every `pilescan-sitl` start 0.24 s
    cell = surface.length_m / unseen.shape[0]
    regions = []
    for side in _wall_sides(unseen.shape, surface.length_m, surface.width_m):
        cells = unseen & side
        join = ndimage.binary_dilation(cells, iterations=max(1, math.ceil(seen_radius_m / cell))) & side
        labels, k = ndimage.label(join)
        regions += [cells & (labels == i) for i in range(1, k + 1)]
    regions.sort(key=lambda m: -int(m.sum()))
    return Gaps(surface, unseen, tuple(r for r in regions if r.any()), surface.source, bridged)


def _bridged(cloud_path: Path, surface: HeightField, seen_radius_m: float) -> np.ndarray | None:
    """The measured cells with no point of the report's cloud within seen_radius_m (module docstring); None without a
    cloud (then the fitted mask alone says what was seen); ValueError (one line) for a cloud that cannot be read, as
    for a damaged surface file: the plan would otherwise leave out gaps without saying so."""
    if surface.measured is None or not cloud_path.is_file():
        return None
    pts = cloud_points_xy(cloud_path)
    nx, _ = surface.measured.shape
    near = within_reach(pts, surface.measured.shape, surface.length_m, surface.width_m, surface.length_m / nx,
                        seen_radius_m)
    return surface.measured & ~near


def _wall_sides(shape: tuple[int, int], length_m: float, width_m: float) -> list[np.ndarray]:
    """The floor's cells by their nearest wall (south, east, north, west): a band of unseen floor along several
    walls (a ring round a pile) is one region per wall, each seen by a leg along its wall."""
    nx, ny = shape
    x = (np.arange(nx)[:, None] + 0.5) * length_m / nx + np.zeros((1, ny))
    y = (np.arange(ny)[None, :] + 0.5) * width_m / ny + np.zeros((nx, 1))
    nearest = np.argmin(np.stack([y, length_m - x, width_m - y, x]), axis=0)
    return [nearest == k for k in range(4)]


@dataclass(frozen=True)
class Leg:
    """A straight pass (W, m)."""

    start: tuple[float, float]
    end: tuple[float, float]

    @property
    def length_m(self) -> float:
        return math.dist(self.start, self.end)

    def reversed(self) -> Leg:
        return Leg(self.end, self.start)


def candidate_legs(region: np.ndarray, storage: Storage, margin_m: float, clearance_m: float) -> list[Leg]:
    """Legs along x and along y over the region's extent (plus margin_m at each end), on its centre line or one
    of its edges, kept clearance_m (or the family's 5 %) from the walls."""
    nx, ny = region.shape
    cx, cy = storage.length_m / nx, storage.width_m / ny
    ix, iy = np.nonzero(region)
    box = ((ix.min() * cx, (ix.max() + 1) * cx), (iy.min() * cy, (iy.max() + 1) * cy))
    size = (storage.length_m, storage.width_m)
    keep = [max(clearance_m, OFFSET_STEPS[0] * size[a]) for a in (0, 1)]
    legs = []
    for along in (0, 1):
        across = 1 - along
        lo_a, hi_a = keep[along], size[along] - keep[along]
        a0 = min(max(box[along][0] - margin_m, lo_a), hi_a)
        a1 = min(max(box[along][1] + margin_m, lo_a), hi_a)
        if a1 - a0 < margin_m:  # a short region at a wall: at least margin_m of leg, inside the bounds
            mid = min(max(0.5 * (a0 + a1), lo_a + 0.5 * margin_m), hi_a - 0.5 * margin_m)
            a0, a1 = mid - 0.5 * margin_m, mid + 0.5 * margin_m
        lo_c, hi_c = keep[across], size[across] - keep[across]
        c0, c1 = box[across]
        tracks = {round(min(max(c0 + f * (c1 - c0), lo_c), hi_c), 3) for f in TRACK_FRACTIONS}
        for t in sorted(tracks):
            p0, p1 = [0.0, 0.0], [0.0, 0.0]
            p0[along], p1[along], p0[across], p1[across] = float(a0), float(a1), float(t), float(t)
            legs.append(Leg((p0[0], p0[1]), (p1[0], p1[1])))
    return legs


def _nearest_end_tour(first: Leg, others: list[Leg]) -> tuple[tuple[float, float], ...]:
    """From first, always on to the nearest end of a leg not yet flown (flown from there), and back."""
    todo = list(others)
    order = [first]
    while todo:
        here = order[-1].end
        i, rev = min(((i, r) for i in range(len(todo)) for r in (False, True)),
                     key=lambda ir: math.dist(here, todo[ir[0]].end if ir[1] else todo[ir[0]].start))
        leg = todo.pop(i)
        order.append(leg.reversed() if rev else leg)
    pts: list[tuple[float, float]] = []
    for leg in order:
        for p in (leg.start, leg.end):
            if not pts or math.dist(pts[-1], p) > 1e-6:
                pts.append(p)
    if len(pts) > 1 and math.dist(pts[-1], pts[0]) <= 1e-6:
        pts.pop()
    return (*pts, pts[0])


def tour_waypoints(legs: list[Leg]) -> tuple[tuple[float, float], ...]:
    """The legs in one closed tour, as short as the nearest-end rule makes it from any leg, either way round;
    one leg alone is flown out and back."""
    tours = [_nearest_end_tour(leg.reversed() if rev else leg, legs[:i] + legs[i + 1:])
             for i, leg in enumerate(legs) for rev in (False, True)]
    return min(tours, key=lambda wp: sum(math.dist(a, b) for a, b in pairwise(wp)))


@dataclass(frozen=True)
class GapCoverage:
    """What the model predicts a re-flight adds."""

    gap_pct: float  # of the report's unseen cells, the share the re-flight covers
    merged_ra_pct: float  # the report's seen cells and these, over the floor: the merged report's R_a
    covered: np.ndarray = field(compare=False)  # (nx, ny) bool: the gap cells covered


def predict_gap_coverage(mission, gaps: Gaps, target: CoverageTarget) -> GapCoverage:
    """The gap cells a mission's beams cover, cast at the report's surface, the merged hull widened by what the
    report measured (module docstring)."""
    hits = floor_hits_w(mission, target.waveform, target.limit, target.rate_hz, target.lever_arm_body_m,
                        gaps.surface)
    cov = coverage_of_hits(hits, mission.storage, target.seen_radius_m, gaps.cell_m, gaps.measured_outline_w())
    got = cov.covered & gaps.unseen
    # the report's fitted cells are in its R_a (eq. 9), the bridged among them
    return GapCoverage(100.0 * got.sum() / gaps.unseen.sum(), 100.0 * (got | gaps.surface.measured).mean(), got)


@dataclass(frozen=True)
class PlannedGaps:
    """The planner's choice: the mission, its prediction, its energy, how many missions it tried."""

    mission: LoopMission
    coverage: GapCoverage
    energy_j: float
    n_regions: int
    n_evaluated: int


def _mission(waypoints, storage: Storage, speed: float, altitude_m: float, yaw_rate: float,
             clearance_m: float, plan: dict | None = None) -> LoopMission:
    return LoopMission(storage, tuple((float(x), float(y)) for x, y in waypoints), speed, altitude_m, yaw_rate,
                       clearance_m, dict(plan or {}))


def plan_fill_gaps(storage: Storage, gaps: Gaps, target: CoverageTarget, altitude_m: float = 12.0,
                   yaw_rate_max_rad_s: float = math.radians(30.0), min_clearance_m: float = 0.5) -> PlannedGaps:
    """The least-energy tour of legs over the gaps (of a report of this building: `load_gaps`) whose predicted
    coverage of the gap cells reaches target.coverage_pct (module docstring); ValueError (one line) when none
    does."""
    legs = list(dict.fromkeys(leg for r in gaps.regions
                              for leg in candidate_legs(r, storage, target.seen_radius_m, min_clearance_m)))
    need = target.coverage_pct / 100.0 * gaps.unseen.sum()
    n_eval = 0
    best, best_reached = None, 0.0

    def tour(chosen: list[Leg], speed: float) -> bool:
        """Check the tour of these legs whole; True when it reaches the target."""
        nonlocal best, best_reached, n_eval
        m = _mission(tour_waypoints(chosen), storage, speed, altitude_m, yaw_rate_max_rad_s, min_clearance_m)
        cov = predict_gap_coverage(m, gaps, target)
        n_eval += 1
        e = mission_energy_j(m, target.energy)
        best_reached = max(best_reached, cov.gap_pct)
        if cov.gap_pct >= target.coverage_pct and (best is None or e < best[0]):
            best = (e, m, cov)
        return cov.gap_pct >= target.coverage_pct

    covers = []  # each candidate flown alone at the fastest speed (its fans farthest apart: the least it covers)
    for leg in legs:
        m = _mission(tour_waypoints([leg]), storage, max(target.speeds_m_s), altitude_m, yaw_rate_max_rad_s,
                     min_clearance_m)
        covers.append(predict_gap_coverage(m, gaps, target).covered)
        n_eval += 1
    for speed in target.speeds_m_s:
        cost = [target.energy.energy_j(leg.length_m, speed, (math.pi / 2, math.pi / 2), yaw_rate_max_rad_s)
                for leg in legs]  # a square turn at each end
        chosen: list[Leg] = []
        got = np.zeros_like(gaps.unseen)
        todo = set(range(len(legs)))
        reached = False
        while todo and not reached:  # greedy cover: the most newly covered gap cells per joule, until the target share
            gain = {i: int((covers[i] & ~got).sum()) / cost[i] for i in todo}
            i = max(sorted(todo), key=lambda k: gain[k])
            if gain[i] <= 0:
                break
            todo.discard(i)
            chosen.append(legs[i])
            got |= covers[i]
            if got.sum() >= need:
                reached = tour(chosen, speed)
        if chosen and not reached and got.sum() < need:
            tour(chosen, speed)  # the legs fall short of the target: the tour's figure for the refusal
    if best is None:
        raise ValueError(f"no re-flight reaches {target.coverage_pct:g} % of the {int(gaps.unseen.sum())} unseen cells "
                         f"(best {math.floor(best_reached * 10.0) / 10.0:.1f} %): lower --gap-coverage, or fly lower")
    e, m, cov = best
    record = {"kind": "fill-gaps", "report": gaps.source, "gap_target_pct": target.coverage_pct,
              "gap_cells": int(gaps.unseen.sum()), "gap_area_m2": float(gaps.unseen.sum() * gaps.cell_m ** 2),
              "bridged_cells": 0 if gaps.bridged is None else int(gaps.bridged.sum()),
              "regions": len(gaps.regions), "predicted_gap_coverage_pct": round(cov.gap_pct, 3),
              "predicted_merged_ra_pct": round(cov.merged_ra_pct, 3), "predicted_energy_j": round(e, 1),
              "seen_radius_m": target.seen_radius_m}
    mission = _mission(m.waypoints, storage, m.speed_m_s, altitude_m, yaw_rate_max_rad_s, min_clearance_m, record)
    return PlannedGaps(mission, cov, e, len(gaps.regions), n_eval)
