"""Does the rangefinder reach what the survey must see? The mission's geometry against the sensor's range.

A sweep perpendicular to the flight sees the floor, and at its ends the walls. From a sensor at height
h over the floor, the beam at servo angle γ meets the floor at range h / cos γ, so the floor is within
a range R only for |γ| <= acos(h / R), out to a lateral reach of sqrt(R² - h²) either side of the track;
beyond that the beam meets a wall (within R if the wall is near enough) or nothing. A 40 m LIDAR-Lite
reaches every floor and wall of a 60 x 40 x 15 m building from 12 m; a 12 m TFMini at that height
reaches 1.5 m of floor either side of the track.

Two figures, both from the empty building (a pile only brings surfaces nearer, so this is the worst
case, and no pile is assumed):
- `in_range_pct`: the share of the sweep, sampled in time over one servo period at points along the
  whole path, whose beam meets the floor or a wall within range;
- `floor_reach_pct`: the share of the floor within the lateral reach of the path (the sweep plane turns
  with the vehicle at the corners, so a disc of that radius about each corner counts too).

`check_range` refuses a mission where most of the sweep or most of the floor is out of range, and warns
(returns the line) when the floor reached is below the level at which the ground report warns that R_a
is low: the floor out of reach is floor the report will have to extrapolate.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from firmware_py.core.waveform import Waveform
from sitl.missions.rectangle import Mission

MOST_PCT = 50.0
"""Below this share of the sweep, or of the floor, in range the mission is refused ("most" out of range)."""
FLOOR_WARN_PCT = 95.0
"""Below this share of the floor in reach the mission is flown with a warning: the ground report's R_a
warning level (`ground.report.LOW_COVERAGE_PCT`; a test keeps the two equal)."""
PATH_SAMPLES = 200
SWEEP_SAMPLES = 181
FLOOR_CELL_M = 0.25


@dataclass(frozen=True)
class RangeCoverage:
    """How much of what the survey must see the sensor reaches (module docstring)."""

    max_range_m: float
    sensor_height_m: float
    floor_reach_m: float  # lateral reach on the floor either side of the track
    in_range_pct: float
    floor_reach_pct: float

    def describe(self) -> str:
        return (f"a {self.max_range_m:g} m rangefinder {self.sensor_height_m:.1f} m above the floor reaches "
                f"{self.floor_reach_m:.1f} m of floor either side of the track: {self.floor_reach_pct:.0f} % of "
                f"the floor, and {self.in_range_pct:.0f} % of the sweep meets the floor or a wall within range")


def _path_points(mission: Mission, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n points evenly along the closed path (W, 2) and the unit direction of flight at each."""
    wp = mission.waypoints_w()
    seg = np.diff(wp, axis=0)
    lengths = np.linalg.norm(seg, axis=1)
    s = (np.arange(n) + 0.5) / n * lengths.sum()
    k = np.minimum(np.searchsorted(np.cumsum(lengths), s), len(seg) - 1)
    start = np.concatenate([[0.0], np.cumsum(lengths)[:-1]])
    u = seg[k] / lengths[k, None]
    return wp[k] + u * (s - start[k])[:, None], u


def beam_ranges_empty(mission: Mission, sensor_height_m: float, gammas_rad: np.ndarray, n_path: int = PATH_SAMPLES,
                      ) -> np.ndarray:
    """(n_path, len(gammas)) ranges from points along the path to the floor or a wall of the empty
    building, the beam in the plane across the flight at each servo angle (0 down, + to the right)."""
    s = mission.storage
    p, u = _path_points(mission, n_path)
    right = np.column_stack([u[:, 1], -u[:, 0]])  # across the track (either side: the sweep is symmetric)
    g = np.asarray(gammas_rad, dtype=float)[None, :]
    horiz, down = np.sin(g), np.cos(g)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_floor = np.where(down > 1e-9, sensor_height_m / down, np.inf)
        t_wall = np.full(np.broadcast_shapes(right[:, :1].shape, g.shape), np.inf)
        for axis, size in ((0, s.length_m), (1, s.width_m)):
            d = right[:, axis:axis + 1] * horiz
            pos = p[:, axis:axis + 1]
            t = np.where(d > 1e-12, (size - pos) / d, np.where(d < -1e-12, -pos / d, np.inf))
            t_wall = np.minimum(t_wall, t)
    return np.minimum(t_floor, t_wall)


def floor_within_reach(mission: Mission, reach_m: float, cell_m: float = FLOOR_CELL_M) -> float:
    """The share (0-1) of the floor within `reach_m` of the flight path (distance to its polyline)."""
    s = mission.storage
    xs = np.arange(cell_m / 2, s.length_m, cell_m)
    ys = np.arange(cell_m / 2, s.width_m, cell_m)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    wp = mission.waypoints_w()
    best = np.full(len(pts), np.inf)
    for a, b in itertools.pairwise(wp):
        ab = b - a
        t = np.clip(((pts - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(pts - (a + t[:, None] * ab), axis=1))
    return float(np.mean(best <= reach_m))


def range_coverage(mission: Mission, max_range_m: float, waveform: Waveform,
                   lever_arm_body_m: tuple[float, float, float] = (0.0, 0.0, 0.10)) -> RangeCoverage:
    """What a rangefinder of `max_range_m` reaches on this mission with this sweep (module docstring)."""
    if not (math.isfinite(max_range_m) and max_range_m > 0):
        raise ValueError(f"max range must be > 0 m, got {max_range_m!r}")
    h = mission.altitude_m - float(lever_arm_body_m[2])  # body z is down: the sensor hangs below the CG
    period = 1.0 / waveform.frequency_hz
    gammas = np.asarray(waveform.angle(np.linspace(0.0, period, SWEEP_SAMPLES, endpoint=False)), dtype=float)
    ranges = beam_ranges_empty(mission, h, gammas)
    in_range = float(np.mean(ranges <= max_range_m))
    reach = math.sqrt(max_range_m ** 2 - h ** 2) if h < max_range_m else 0.0
    return RangeCoverage(max_range_m, h, reach, 100.0 * in_range, 100.0 * floor_within_reach(mission, reach))


def check_range(mission: Mission, max_range_m: float, waveform: Waveform,
                lever_arm_body_m: tuple[float, float, float] = (0.0, 0.0, 0.10)) -> str | None:
    """Refuse (ValueError) a mission whose sweep or floor is mostly out of the rangefinder's range; return a
    warning line when part of the floor is out of reach (None when all is)."""
    c = range_coverage(mission, max_range_m, waveform, lever_arm_body_m)
    fix = ("fly lower (the pile's top and the clearance allowing), choose P_traj so that a leg passes "
           "within that reach of every part of the floor, or survey a smaller bay")
    if c.in_range_pct < MOST_PCT or c.floor_reach_pct < MOST_PCT:
        raise ValueError(f"the floor and walls are mostly out of range: {c.describe()}; {fix}")
    if c.floor_reach_pct < FLOOR_WARN_PCT:
        return f"part of the floor is out of range: {c.describe()}; the report will extrapolate the rest ({fix})"
    return None
