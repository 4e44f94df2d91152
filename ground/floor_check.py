"""The floor's level as the flight measured it, against the storage frame's z = 0.

Every height the report computes is the LiDAR's origin plus its beam: the autopilot's altitude, the lever arm from
the autopilot to the LiDAR (log header `lever_arm_body_m`), and the range along the beam. An error in the first two
that stays the same all flight moves every point up or down by the same amount, the floor and the piles alike, and
the volume by that height times the whole building's floor area (every cell's height is measured from z = 0): a lever
arm's z entered 0.2 m off read a 30 x 20 m survey 6.8 % low. The pose correction takes such an error out when its
height brings the floor it rests on onto z = 0 by more than the floor's sightings scatter (each one knot interval's
median in a cell), up from below always, down from above only where the floor is level and within the barometer's
walk over the flight (`ground.pose_decisions.floor_brought_on`); under a range or pointing noise of centimetres to
decimetres a few centimetres do not pass that, and the walls, vertical, never see a height. What it leaves below
z = 0 is this check's: the floor a few centimetres low lies within the points' tolerance of z = 0, so the surface
keeps it as a slightly sunken floor.

The floor is the lowest large flat surface in the building: `ground.base.fit_floor_plane`'s plane (the most points
within their noise, none below) through the points that are neither wall nor roof, with the points under z = 0 kept
(the surface leaves out those beyond their tolerance as glitches; here they may be the floor itself) finds the floor;
the median height of the points on a level floor there, with a median's standard error, is its level. A plane
with more points under it than its noise puts there, and a floor's worth of points lower still, lies on material
(`ground.base.on_material`: a pile's long flank through a corner of floor at its foot): no floor is reported then.

Only a floor *below* z = 0 is warned of. The storage frame puts z = 0 on the floor's lowest corner, so nothing
solid lies below it; a floor seen above z = 0 everywhere cannot be told from material covering the whole floor (a
flat pile wall to wall, measured on the evaluation set: the lowest flat surface up to 4.3 m up), so that is left to
the surveyor's eye on the height map. Measured on the 1,512 error-free evaluation runs: the floor never lay more
than 1.0 cm below z = 0 (at most 4.2 of its standard errors; Appendix A's pointing noise makes those errors too
small). So the warning needs both: the level more than N_SIGNIFICANT standard errors below z = 0, and the volume it
moves (level x floor area) larger than the volume's own 90 % interval's half-width, which does not hold it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from firmware_py.core.cli import UserError
from firmware_py.core.storage import Storage
from ground.base import MIN_FLOOR_POINTS, FloorFall, fit_floor_plane, on_material, points_below
from ground.pointcloud import N_SIGMA, Cloud, SensorErrorModel, plane_tolerances_m
from ground.smoothing import cloud_vertical_sigma_m
from ground.surface import Grid
from ground.uncertainty import cell_index, over_surface_m3
from ground.volume_warnings import OtherReading

N_SIGNIFICANT = 3.0
"""A floor lies below z = 0 when its level is this many standard errors below it (and the volume it moves matters)."""
HUBER_ROUNDS = 10
"""Reweighting rounds of `floor_fall`'s robust plane (its weights settle in a few)."""
HUBER_K = 1.5
"""Huber's constant, in robust sigmas of the residuals."""


@dataclass(frozen=True)
class FloorLevel:
    """The floor the sweeps saw: its level where they saw it, and the plane that found it."""

    level_m: float  # the median height of the floor's points, storage frame z (the floor is z = 0)
    std_error_m: float  # its standard error (one value per cell: a cell's points share the pose's error)
    tilt_deg: float  # the plane's (a floor's fall, or a pile's toe that tilted it)
    n_points: int  # points within their band of the level floor
    cover_pct: float  # the building's cells that hold a floor point, %
    n_under_tolerance: int  # points more than their tolerance below z = 0: the surface left them out as glitches
    fall: FloorFall = field(default_factory=lambda: FloorFall(0.0, 0.0))  # away from material (`floor_fall`)

    @property
    def below(self) -> bool:
        """The floor lies significantly below z = 0 (whether it matters is `floor_warning`'s question)."""
        return self.level_m < -N_SIGNIFICANT * self.std_error_m

    def as_dict(self) -> dict:
        return {"level_m": self.level_m, "std_error_m": self.std_error_m, "tilt_deg": self.tilt_deg,
                "n_points": self.n_points, "cover_pct": self.cover_pct, "n_under_tolerance": self.n_under_tolerance,
                "fall_pct": self.fall.fall_pct, "rise_azimuth_deg": self.fall.rise_azimuth_deg,
                "laid_to_fall": self.fall.laid_to_fall}


def measure_floor(cloud: Cloud, structure: np.ndarray, storage: Storage, err: SensorErrorModel,
                  grid: Grid) -> FloorLevel | None:
    """The floor's level (module docstring) from the survey's placed cloud and its structure mask
    (`ground.pointcloud.structure_mask`); None when no plausible floor is seen (too few points, a plane too steep
    for a floor, a plane that lies on material with points under it: a floor the material hides, in view at most at
    its foot)."""
    p = cloud.points_w
    if len(p) == 0:
        return None
    tol_z = plane_tolerances_m(cloud, err)[:, 2]
    under = p[:, 2] < -tol_z  # in the structure mask as glitches: here they may be the floor
    keep = (~structure | under) & (p[:, 2] < storage.height_m - tol_z)
    if not keep.any():
        return None
    sigma = cloud_vertical_sigma_m(cloud, err, keep)
    try:
        plane = fit_floor_plane(p[keep], sigma, grid, N_SIGMA)
    except UserError:
        return None
    # The floor's level is not the plane's height anywhere: a floor seen only around a large pile leaves the plane's
    # tilt to the pile's toes within its band (measured: 0.47 deg, the plane +8.6 cm at the centre of a 30 x 20 m
    # building whose floor was seen on 5 % of its cells, +2.1 cm at its points' centroid; on 90 floor points of a
    # thinned log, 1.6 deg). It is the median height of the points within their band of a *level* floor, started at
    # the plane's points' median and re-selected until they stop changing: the toes are a few points above a floor
    # that holds most of them, which a median passes over (+0.13 cm on that flight). Its standard error is a median's:
    # 1.25 of the points' robust spread over the root of the cells they fill (a cell's points share one pose error).
    pts, band = p[keep], N_SIGMA * sigma
    level = float(np.median(pts[plane.inliers, 2]))
    if on_material(points_below(pts, sigma, plane, N_SIGMA), pts[:, 2], band, level):
        return None
    on = plane.inliers
    for _ in range(20):  # then level: the points within their band of a level floor there, until they stop changing
        now = np.abs(pts[:, 2] - level) <= band
        if not now.any() or np.array_equal(now, on):
            break
        on, level = now, float(np.median(pts[now, 2]))
    q = pts[on]
    ix, iy = cell_index(q, grid)
    n_cells = len(np.unique(ix * grid.shape[1] + iy))
    spread = 1.4826 * float(np.median(np.abs(q[:, 2] - level)))
    se = 1.2533 * spread / math.sqrt(max(1, n_cells))
    cover = 100.0 * n_cells / (grid.shape[0] * grid.shape[1])
    # the fall: from the plane's points away from the material above it (`floor_fall`), else the plane's own
    above = pts[:, 2] - plane.at(pts[:, 0], pts[:, 1]) > band
    fall = floor_fall(pts[plane.inliers], pts[above, :2], 1.0 / np.maximum(sigma[plane.inliers], 1e-6) ** 2)
    fall = fall or plane.fall
    return FloorLevel(level, se, plane.tilt_deg, len(q), cover, int(under.sum()), fall)


def floor_fall(floor_w: np.ndarray, material_xy: np.ndarray, weights: np.ndarray | None = None) -> FloorFall | None:
    """The fall of a plane fitted to the floor points (N, 3) that lie farther than half of them from material
    (material_xy, (M, 2): the points above the floor): weighted least squares (weights, default equal), Huber-reweighted
    so that a stray point does not tilt it. A pile's toe lies within the floor's band beside the pile and tilts a plane
    fitted through it (0.53 % on a level floor of the evaluation set), while a floor laid to a fall rises as much far
    from the piles as near them. All the floor points when no material is given; None when too few lie far off or they
    do not span a plane."""
    from scipy.spatial import cKDTree
    pts = np.asarray(floor_w, dtype=float)
    w0 = np.ones(len(pts)) if weights is None else np.asarray(weights, dtype=float)
    far = np.ones(len(pts), dtype=bool)
    if len(material_xy) and len(pts):
        distance = cKDTree(np.asarray(material_xy, dtype=float)).query(pts[:, :2])[0]
        far = distance >= np.median(distance)
    pts, w0 = pts[far], w0[far]
    a = np.column_stack([np.ones(len(pts)), pts[:, :2]])
    if len(pts) < MIN_FLOOR_POINTS or np.linalg.matrix_rank(a) < 3:
        return None
    w = w0
    for _ in range(HUBER_ROUNDS):
        sw = np.sqrt(w)
        coef = np.linalg.lstsq(a * sw[:, None], pts[:, 2] * sw, rcond=None)[0]
        r = np.abs(pts[:, 2] - a @ coef)
        scale = 1.4826 * float(np.median(r))
        if not scale > 0:
            break
        w = w0 * np.minimum(1.0, HUBER_K * scale / np.maximum(r, 1e-12))
    return FloorFall(float(coef[1]), float(coef[2]))


def floor_lift_m(floor: FloorLevel | None, storage: Storage, interval_half_m3: float | None) -> float | None:
    """How far every height must be lifted to put the floor on z = 0, when the floor lies below it by more than its
    noise and by a volume (level x floor area) more than interval_half_m3 (None: no interval, significance alone);
    None when it does not."""
    if floor is None or not floor.below:
        return None
    if interval_half_m3 is not None and -floor.level_m * storage.floor_area_m2 <= interval_half_m3:
        return None
    return -floor.level_m


def floor_other_reading(floor: FloorLevel | None, storage: Storage, heights: np.ndarray, grid: Grid,
                        volume_m3: float, interval_m3: tuple[float, float] | None) -> OtherReading | None:
    """The verdict's other reading when the floor lies below z = 0 as `floor_warning` warns: the volume with every
    surfaced height lifted by as much (what --lever-arm with the warning's figure gives, to the fill's edges), its
    interval moved alike. None when no lift is warned of."""
    half = None if interval_m3 is None else (interval_m3[1] - interval_m3[0]) / 2.0
    lift = floor_lift_m(floor, storage, half)
    if lift is None:
        return None
    moved = over_surface_m3(lift, heights, grid)
    return OtherReading(-moved, volume_m3 + moved,
                        None if interval_m3 is None else (interval_m3[0] + moved, interval_m3[1] + moved),
                        condition=f"every height is {lift:.2f} m low (the floor seen below z = 0: a lever arm's z or "
                                  "an altitude reference off by that much)")


def floor_warning(floor: FloorLevel | None, storage: Storage, lever_arm_body_m: np.ndarray,
                  interval_half_m3: float | None) -> str | None:
    """One warning when the floor lies below z = 0 by more than its noise and by a volume the interval does not hold
    (module docstring), naming the two causes and the --lever-arm that would move every point back up; None else.
    interval_half_m3: the volume's 90 % interval's half-width (None: no interval, then significance alone)."""
    if floor_lift_m(floor, storage, interval_half_m3) is None:
        return None
    moved = -floor.level_m * storage.floor_area_m2
    lever = np.asarray(lever_arm_body_m, dtype=float)
    z_new = float(lever[2]) + floor.level_m  # a lever arm less far down lifts every point by as much
    arg = f"--lever-arm {lever[0]:g} {lever[1]:g} {z_new:.2f}"
    dropped = (f"; {floor.n_under_tolerance:,} lay too far below z = 0 for the surface, which left them out as "
               "glitches" if floor.n_under_tolerance else "")
    return (f"the floor the sweeps saw lies {-floor.level_m:.2f} m below z = 0 (+/-{floor.std_error_m * 1000:.1f} mm, "
            f"{floor.n_points:,} floor points over {floor.cover_pct:.0f} % of the building{dropped}): every height "
            f"is that much low, and the volume about {moved:,.0f} m³ low, more than its interval allows. A height off "
            f"by a constant comes from the lever arm's z (the report placed the LiDAR {_below(float(lever[2]))} the "
            f"autopilot's origin) or from the autopilot's altitude reference: if the LiDAR sits {_below(z_new)} it, "
            f"or the altitude read {-floor.level_m:.2f} m low all flight, report again with {arg} (it lifts every "
            "point by as much); if the building's floor really lies below its z = 0, use --base fitted-floor")


def _below(z_m: float) -> str:
    """A lever arm's z (body frame, down positive) in words."""
    return f"{abs(z_m):.2f} m {'below' if z_m >= 0 else 'above'}"


def fall_warning(floor: FloorLevel | None, height_moved_m: float) -> str | None:
    """When the pose correction moved the height (height_moved_m: the most it moved it, m) and the floor seen falls
    (`FloorFall.laid_to_fall`): the correction solves the height from the floor as the plane z = 0 and reads a floor
    laid to a fall as an altitude error (the four cones on a floor falling 1.5 %: flown without pose error, every
    point lowered 0.12 m until the floor's route refused a floor it would leave falling; flown with a `flow` drift, the
    height solved from the floor flattened it: docs/design-notes.md). None otherwise."""
    if floor is None or not floor.fall.laid_to_fall or not height_moved_m > 0.0:
        return None
    return (f"the pose correction moved the height by up to {height_moved_m:.2f} m taking the floor for the level "
            f"plane z = 0, but the floor the sweeps saw rises {floor.fall.fall_pct:.1f} % towards "
            f"{round(floor.fall.rise_azimuth_deg):d} deg from x: on a floor laid to a fall the correction reads the "
            "fall as an error of the altitude reference. If the logged pose is known good, report again with "
            "--no-pose-correction; measure the volume from the floor itself with --base fitted-floor")
