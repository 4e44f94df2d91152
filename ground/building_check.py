"""The building's size as the flight measured it, against the log header's.

The ground station places the floor and walls where the log header's building says (`Storage`), and the pose
correction and the mount's self-calibration move the flight until the structure sits there. A building entered
a few decimetres off (a tape laid along a wall's foot kerb, a plan's nominal size, the other bay's length) is then
"corrected" into the survey: the correction stretches the trajectory towards walls that are not there and the pile
with it, by about the size's error over the size (measured: 0.3 m on 30 m read the volume 1.6 % high, 1 m 5.7 %,
each truth outside its interval and nothing said but the correction's size).

A sweep that crosses the building sees both opposite walls at once, from one pose: the distance between them does
not depend on where the pose puts the vehicle (a shift moves both alike; a heading error of a degree shortens it by
a few millimetres). So each sweep that holds a straight, steep stretch up each of two opposite walls
(`ground.plane_stretches.wall_stretches`: steeper than any pile stands, beside the wall within a heading error's
reach) measures the building's length or width; their median over the flight, with its standard error from their
scatter, is compared with the header's.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

from firmware_py.core.storage import Storage
from ground.plane_stretches import CHORD_HALF, STEEPEST_PILE_DEG, sweep_ids, wall_stretches
from ground.pose_knots import PoseCorrectionOptions

MIN_WALL_POINTS = 5
"""A sweep measures the distance between two walls when it holds at least this many wall-stretch points on each."""
MIN_SWEEPS = 5
"""Fewer sweeps across the building than this measure nothing (one sweep's glitch would be the answer)."""
REACH_M = PoseCorrectionOptions.max_position_error_m
"""How far from the header's wall a wall is looked for: the pose correction's own reach, the farthest it would move
the flight towards a wall."""
WALL_RELIEF_M = 0.05
"""How far a real wall's face stands in and out of its plane (pilasters' faces, cladding, a sweep over a fixing):
a side's outermost group of points spans its 3 sigmas and this."""
N_SIGNIFICANT = 3.0
"""A size differs from the header's when it lies this many of its standard errors away (and by MIN_SIZE_ERROR_REL)."""
MIN_SIZE_ERROR_REL = 0.001
"""Nor is a size within a tenth of a percent of the header's worth a word: stretched by that, a survey's volume moves
by less than any target the report is judged by (a drifting pose's, 0.3 pp), and real walls bow and lean by as much."""


class Axis(enum.Enum):
    """The building's two horizontal dimensions, each between a pair of opposite walls."""

    LENGTH = "length"  # x: the walls x = 0 and x = L
    WIDTH = "width"  # y: the walls y = 0 and y = W

    @property
    def walls(self) -> str:
        return "x = 0 and x = L" if self is Axis.LENGTH else "y = 0 and y = W"


@dataclass(frozen=True)
class SizeCheck:
    """One dimension measured between its two walls, per sweep that saw both."""

    axis: Axis
    header_m: float
    measured_m: float | None  # median over the sweeps; None: too few sweeps saw both walls
    std_error_m: float | None
    n_sweeps: int

    @property
    def off_m(self) -> float | None:
        return None if self.measured_m is None else self.measured_m - self.header_m

    @property
    def differs(self) -> bool:
        """Significant against its own scatter, and large enough to matter."""
        off, se = self.off_m, self.std_error_m
        return off is not None and se is not None and abs(off) > max(N_SIGNIFICANT * se,
                                                                     MIN_SIZE_ERROR_REL * self.header_m)

    def as_dict(self) -> dict:
        return {"header_m": self.header_m, "measured_m": self.measured_m, "std_error_m": self.std_error_m,
                "sweeps": self.n_sweeps, "differs": self.differs}


def outermost(x: np.ndarray, band_m: float) -> float | None:
    """The median of the outermost group of at least MIN_WALL_POINTS values within band_m of each other, from the
    low end (nothing stands behind a wall: a box's face or a column in front of it is further in); None without
    one."""
    x = np.sort(np.asarray(x, dtype=float))
    n = MIN_WALL_POINTS
    if len(x) < n:
        return None
    start = np.flatnonzero(x[n - 1:] - x[:len(x) - n + 1] <= band_m)
    if not len(start):
        return None
    lo = x[start[0]]
    return float(np.median(x[(x >= lo) & (x <= lo + band_m)]))


def measure_size(points_w: np.ndarray, wall: np.ndarray, sweep: np.ndarray, axis: Axis, storage: Storage,
                 band_m: float) -> SizeCheck:
    """The distance between the two walls of `axis` in each sweep that holds a group of at least MIN_WALL_POINTS
    wall-stretch points on each side (wall: the mask of steep straight stretches; sweep: `sweep_ids`), each side's
    outermost group (`outermost`, band_m wide); their median over the sweeps and its standard error (the sweeps'
    robust scatter over the root of their number)."""
    c = 0 if axis is Axis.LENGTH else 1
    size = storage.length_m if axis is Axis.LENGTH else storage.width_m
    other = storage.width_m if axis is Axis.LENGTH else storage.length_m
    p = np.asarray(points_w, dtype=float)
    # beside one of this axis's walls and not nearer one of the other two (a corner's stretch is either's)
    to_low, to_high = p[:, c], size - p[:, c]
    to_other = np.minimum(p[:, 1 - c], other - p[:, 1 - c])
    low = wall & (to_low < to_high) & (np.abs(to_low) < to_other)
    high = wall & (to_high <= to_low) & (np.abs(to_high) < to_other)
    seps = []
    idx = np.flatnonzero(low | high)  # in time order, so each sweep's are together (`sweep_ids` counts up)
    for one in np.split(idx, np.flatnonzero(np.diff(sweep[idx])) + 1):  # each sweep's points beside these walls
        lo = outermost(p[one[low[one]], c], band_m)
        hi = outermost(-p[one[high[one]], c], band_m)
        if lo is not None and hi is not None:
            seps.append(-hi - lo)
    if len(seps) < MIN_SWEEPS:
        return SizeCheck(axis, size, None, None, len(seps))
    a = np.asarray(seps)
    med = float(np.median(a))
    scatter = 1.4826 * float(np.median(np.abs(a - med)))
    se = math.sqrt(math.pi / 2.0) * scatter / math.sqrt(len(a))  # a median's, sqrt(pi/2) times the mean's
    return SizeCheck(axis, size, med, se, len(a))


def check_building(points_w: np.ndarray, t_s: np.ndarray | None, sweep_dir: np.ndarray | None,
                   beam_w: np.ndarray, sigma_m: np.ndarray, storage: Storage) -> tuple[SizeCheck, SizeCheck] | None:
    """The building's length and width as the sweeps measured them (None without the points' times and sweep
    directions, which a stretch of sweep needs). beam_w: each point's vector from the vehicle; sigma_m: each point's
    1-sigma error (as `wall_stretches` takes it)."""
    if t_s is None or sweep_dir is None or len(t_s) < 2:
        return None
    dt = float(np.median(np.diff(t_s)))
    p = np.asarray(points_w, dtype=float)
    sweep = sweep_ids(t_s, sweep_dir, dt)
    # Only the points of sweeps that reach across the building, within REACH_M of both walls, can measure it, and
    # only those whose chord is steep can be a wall's (a straight stretch's chord is its line): the line fits are
    # this check's cost (40,000 of them on a paper flight's 80,000 points, whose walls are 40 m apart and beyond
    # the LIDAR-Lite's reach), so the rest are not fitted.
    starts = np.flatnonzero(np.r_[True, np.diff(sweep) != 0])
    span = [np.maximum.reduceat(p[:, c], starts) - np.minimum.reduceat(p[:, c], starts) for c in (0, 1)]
    across = ((span[0] >= storage.length_m - 2.0 * REACH_M) | (span[1] >= storage.width_m - 2.0 * REACH_M))
    candidate = np.repeat(across, np.diff(np.r_[starts, len(p)]))
    h = CHORD_HALF
    if len(p) > 2 * h:
        chord = p[2 * h:] - p[:-2 * h]
        candidate[h:-h] &= (np.abs(chord[:, 2])
                            >= math.sin(math.radians(STEEPEST_PILE_DEG)) * np.linalg.norm(chord, axis=1))
    wall = wall_stretches(p, t_s, sweep_dir, beam_w, sigma_m, storage.length_m, storage.width_m, dt,
                          only=candidate, reach_m=REACH_M)
    band = 3.0 * float(np.median(sigma_m)) + WALL_RELIEF_M
    return (measure_size(p, wall, sweep, Axis.LENGTH, storage, band),
            measure_size(p, wall, sweep, Axis.WIDTH, storage, band))


def size_warning(checks: tuple[SizeCheck, SizeCheck] | None, storage: Storage,
                 mount_doubtful: bool = False) -> str | None:
    """One warning when the sweeps measure the building other than the header says, with the --storage that would
    report it as measured; None when they agree or measured nothing. mount_doubtful: the self-calibration found the
    floor and walls off their planes whatever the mount, so the sweeps' angles may be what is wrong (measured: a
    header boresight 14-17 deg wrong measured the width 0.6-1.3 m short), and that is named first."""
    if checks is None:
        return None
    off = [c for c in checks if c.differs]
    if not off:
        return None
    said = "; ".join(f"the walls {c.axis.walls} are {c.measured_m:.2f} m apart (+/-{c.std_error_m * 100:.1f} cm, "
                     f"{c.n_sweeps} sweeps that see both), the log header says {c.header_m:g} m" for c in off)
    dims = {c.axis: c.measured_m for c in off}
    length = dims.get(Axis.LENGTH, storage.length_m)
    width = dims.get(Axis.WIDTH, storage.width_m)
    stretch = max(abs(c.off_m) / c.header_m for c in off) * 100.0
    storage_arg = f"--storage {length:.2f}x{width:.2f}x{storage.height_m:g}"
    head = (f"the building is not the size the log header says: {said}. The floor and walls are placed where the "
            f"header puts them, and a pose correction moves the flight towards them, stretching the survey and the "
            f"volume by up to about {stretch:.1f} %")
    if mount_doubtful:
        return (f"{head}. The self-calibration could not fit the floor and walls with any mount either, so the "
                "sweeps' angles may be what is wrong: check the log header's boresight and the servo's calibration "
                f"first; if they are right and the header's building is wrong, report again with {storage_arg}")
    return (f"{head}: if the header's building is wrong, report again with {storage_arg}; if it is right, the "
            "rangefinder's range or the servo's angles are off")
