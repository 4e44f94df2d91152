"""Does the rangefinder reach what the survey must see? The mission's geometry against the sensor's range.

A sweep perpendicular to the flight sees the floor, and at its ends the walls. From a sensor at height
h over the floor, the beam at servo angle γ meets the floor at range h / cos γ, so the floor is within
a range R only for |γ| <= acos(h / R), out to a lateral reach of sqrt(R² - h²) either side of the track;
beyond that the beam meets a wall (within R if the wall is near enough) or nothing. A 40 m LIDAR-Lite
reaches every floor and wall of a 60 x 40 x 15 m building from 12 m; a 12 m TFMini at that height
reaches 1.5 m of floor either side of the track.

The range is the one the flight's sensing gives (`RangeLimit`): with ideal sensing every surface within
the rated range echoes; with the datasheet noise (`--sensor-noise datasheet`) the rated range is stated
on a bright target, and the return model (`firmware_py.core.sensor.ReturnModel`) shrinks it to
R(i) = R_rated sqrt(rho cos i / rho_ref) on the survey's surfaces, beyond (1 - ramp) R(i) of which
echoes start to fail. The planning takes that certain-echo range, R_c(i) = (1 - ramp) R(i), at each
beam's incidence i. On a bare floor from height h, a beam at servo angle gamma has range h / cos gamma
and incidence gamma, so it is reached while (h / cos gamma)^(3/2) <= R_c(0) h^(1/2): out to a range
R_c(0)^(2/3) h^(1/3), and no floor at all when h > R_c(0). The reach across the track is widest from
h = R_c(0) / 3^(3/4). A wall d across from the track is reached by the level beam (normal incidence)
when d <= R_c(0).

Two figures, both from the empty building (a pile only brings surfaces nearer, so this is the worst
case for range, and no pile is assumed; a pile's flanks may meet the beam more obliquely than the floor
would, which this does not see):
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

from firmware_py.core.sensor import RangefinderSpec, ReturnModel, sure_echo_range_m
from firmware_py.core.sensor_noise import SensorNoise, SensorNoiseModel
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
class RangeLimit:
    """How far the planning counts on an echo (module docstring).

    Attributes:
        rated_range_m: the datasheet's range (`RangefinderSpec.max_range_m`).
        returns: the return model of the flight's sensing, or None when every surface within the rated
            range echoes (ideal sensing, the paper's Appendix A).
        model: the sensor's name, for the messages.
    """

    rated_range_m: float
    returns: ReturnModel | None = None
    model: str = "rangefinder"

    def __post_init__(self) -> None:
        if not (isinstance(self.rated_range_m, int | float) and math.isfinite(self.rated_range_m)
                and self.rated_range_m > 0):
            raise ValueError(f"max range must be > 0 m, got {self.rated_range_m!r}")

    def reach_m(self, cos_incidence: np.ndarray | float = 1.0) -> np.ndarray:
        """The farthest certain echo at this incidence: the rated range, or (1 - ramp) of the return
        model's effective range on the assumed surfaces."""
        return sure_echo_range_m(self.rated_range_m, self.returns, cos_incidence)

    @property
    def normal_reach_m(self) -> float:
        """The reach at normal incidence (a floor straight below, a wall met square)."""
        return float(self.reach_m(1.0))

    def floor_range_m(self, height_m: float) -> float:
        """The farthest bare-floor point the beam reaches from this height, along the beam (0: none)."""
        reach = self.normal_reach_m
        if height_m > reach:
            return 0.0
        if self.returns is None:
            return reach
        return reach ** (2 / 3) * height_m ** (1 / 3)

    def floor_reach_m(self, height_m: float) -> float:
        """The bare floor's lateral reach either side of the track from this height (0: none)."""
        r = self.floor_range_m(height_m)
        return math.sqrt(max(0.0, r * r - height_m * height_m)) if r > 0 else 0.0

    @property
    def widest_floor_height_m(self) -> float:
        """The height over the floor from which the floor's lateral reach is widest (module docstring);
        with ideal sensing the lower the wider (0)."""
        return self.normal_reach_m / 3 ** 0.75 if self.returns is not None else 0.0

    def describe(self) -> str:
        if self.returns is None:
            return f"{self.rated_range_m:g} m (the {self.model}'s rated range)"
        r = self.returns
        return (f"{self.normal_reach_m:.1f} m (the {self.model}'s {self.rated_range_m:g} m at "
                f"{100 * r.reference_reflectance:.0f} % reflectance, on {100 * r.target_reflectance:.0f} % "
                "reflective surfaces: its datasheet return model, certain echoes)")


def planning_limit(spec: RangefinderSpec, sensor_noise: SensorNoiseModel | str = SensorNoiseModel.NONE,
                   ) -> RangeLimit:
    """The range to plan with for this rangefinder and sensor noise model (ValueError: unknown model)."""
    return RangeLimit(spec.max_range_m, SensorNoise.of(sensor_noise, spec).returns, spec.model)


@dataclass(frozen=True)
class RangeCoverage:
    """How much of what the survey must see the sensor reaches (module docstring)."""

    max_range_m: float  # the normal-incidence reach the planning uses
    sensor_height_m: float
    floor_reach_m: float  # lateral reach on the floor either side of the track
    in_range_pct: float
    floor_reach_pct: float
    limit: RangeLimit | None = None
    near_wall_m: float = 0.0  # the farthest wall a leg runs along (the sweep's end meets it)

    @property
    def floor_reach_deg(self) -> float:
        """The servo angle beyond which the sweep meets no bare floor within reach."""
        return math.degrees(math.atan2(self.floor_reach_m, self.sensor_height_m)) if self.floor_reach_m else 0.0

    def out_of_reach(self) -> str:
        """What the sensor does not reach: the floor at the sweep's ends, walls beyond the reach."""
        parts = [f"the floor beyond +-{self.floor_reach_deg:.0f} deg of the sweep" if self.floor_reach_m > 0
                 else "all of the floor, even straight below"]
        if self.near_wall_m > self.max_range_m:
            parts.append(f"the walls {self.near_wall_m:.1f} m from the legs")
        return ", ".join(parts)

    def describe(self) -> str:
        limit = self.limit or RangeLimit(self.max_range_m)
        return (f"planning range {limit.describe()}: {self.sensor_height_m:.1f} m above the floor the sensor "
                f"reaches {self.floor_reach_m:.1f} m of floor either side of the track; out of reach: "
                f"{self.out_of_reach()}; {self.floor_reach_pct:.0f} % of the floor and {self.in_range_pct:.0f} % "
                "of the sweep in reach")

    def remedy(self, mission: Mission) -> str:
        """What to change: the height over the floor and the legs' offset that bring the floor in reach."""
        limit = self.limit or RangeLimit(self.max_range_m)
        s = mission.storage
        below = f"the floor below is reached from at most {limit.normal_reach_m:.1f} m above it"
        if limit.returns is not None:
            below += (f", the floor across widest ({limit.floor_reach_m(limit.widest_floor_height_m):.1f} m) from "
                      f"{limit.widest_floor_height_m:.1f} m")
        h, hw = self.sensor_height_m, limit.widest_floor_height_m
        move = "fly lower" if h > hw else f"fly nearer {hw:.1f} m above the floor"
        text = f"{move} ({below}; the pile's top and the clearance allowing)"
        reach = self.floor_reach_m
        if reach <= 0:
            return text
        # The bare floor is all reached when the legs are within reach of the walls (P_traj L <= reach) and
        # of the bay's middle line ((1 - 2 P_traj) W / 2 <= reach).
        lo = math.ceil(100.0 * max(0.0, 0.5 - reach / min(s.length_m, s.width_m)))
        hi = math.floor(100.0 * min(0.5, reach / max(s.length_m, s.width_m)))
        if lo <= hi:
            return (text + f", or choose P_traj {lo}-{hi} % (the legs within {reach:.1f} m of the walls and of the "
                    "middle)")
        return (text + "; from this height no P_traj reaches all of the bare floor: with the legs within "
                f"{reach:.1f} m of the walls (P_traj <= {hi} %) the floor is reached along them, where a pile's foot "
                f"lies; or survey a bay at most {4 * reach:.0f} m wide")


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


def beam_hits_empty(mission: Mission, sensor_height_m: float, gammas_rad: np.ndarray, n_path: int = PATH_SAMPLES,
                    ) -> tuple[np.ndarray, np.ndarray]:
    """(n_path, len(gammas)) ranges from points along the path to the floor or a wall of the empty
    building, the beam in the plane across the flight at each servo angle (0 down, + to the right), and
    the cosine of the beam's incidence on the surface it meets."""
    s = mission.storage
    p, u = _path_points(mission, n_path)
    right = np.column_stack([u[:, 1], -u[:, 0]])  # across the track (either side: the sweep is symmetric)
    g = np.asarray(gammas_rad, dtype=float)[None, :]
    horiz, down = np.sin(g), np.cos(g)
    shape = np.broadcast_shapes(right[:, :1].shape, g.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.broadcast_to(np.where(down > 1e-9, sensor_height_m / down, np.inf), shape)
        cos_i = np.broadcast_to(np.abs(down), shape)
        for axis, size in ((0, s.length_m), (1, s.width_m)):
            d = right[:, axis:axis + 1] * horiz
            pos = p[:, axis:axis + 1]
            t_wall = np.where(d > 1e-12, (size - pos) / d, np.where(d < -1e-12, -pos / d, np.inf))
            wall_first = t_wall < t
            t = np.where(wall_first, t_wall, t)
            cos_i = np.where(wall_first, np.abs(d), cos_i)
    return t, cos_i


def beam_ranges_empty(mission: Mission, sensor_height_m: float, gammas_rad: np.ndarray, n_path: int = PATH_SAMPLES,
                      ) -> np.ndarray:
    """The ranges of `beam_hits_empty`."""
    return beam_hits_empty(mission, sensor_height_m, gammas_rad, n_path)[0]


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


def _near_wall_m(mission: Mission) -> float:
    """The farthest of the walls the legs run along, from their legs (P_traj of L and of W)."""
    wp = mission.waypoints_w()
    s = mission.storage
    x, y = wp[:, 0], wp[:, 1]
    return float(max(min(x.min(), s.length_m - x.max()), min(y.min(), s.width_m - y.max())))


def range_coverage(mission: Mission, max_range_m: float | RangeLimit, waveform: Waveform,
                   lever_arm_body_m: tuple[float, float, float] = (0.0, 0.0, 0.10),
                   returns: ReturnModel | None = None) -> RangeCoverage:
    """What a rangefinder reaches on this mission with this sweep (module docstring): `max_range_m` the
    rated range (with `returns`, the return model of the flight's sensing) or a `RangeLimit`."""
    limit = max_range_m if isinstance(max_range_m, RangeLimit) else RangeLimit(max_range_m, returns)
    h = mission.altitude_m - float(lever_arm_body_m[2])  # body z is down: the sensor hangs below the CG
    period = 1.0 / waveform.frequency_hz
    gammas = np.asarray(waveform.angle(np.linspace(0.0, period, SWEEP_SAMPLES, endpoint=False)), dtype=float)
    ranges, cos_i = beam_hits_empty(mission, h, gammas)
    in_range = float(np.mean(ranges <= limit.reach_m(cos_i) * (1 + 1e-9)))
    reach = limit.floor_reach_m(h)
    return RangeCoverage(limit.normal_reach_m, h, reach, 100.0 * in_range, 100.0 * floor_within_reach(mission, reach),
                         limit, _near_wall_m(mission))


def check_range(mission: Mission, max_range_m: float | RangeLimit, waveform: Waveform,
                lever_arm_body_m: tuple[float, float, float] = (0.0, 0.0, 0.10),
                returns: ReturnModel | None = None) -> str | None:
    """Refuse (ValueError) a mission whose sweep or floor is mostly out of the rangefinder's range; return a
    warning line when part of the floor is out of reach (None when all is). `max_range_m` and `returns`
    as in `range_coverage`: pass the flight's return model, so the planning uses the range its surfaces
    give, not the datasheet's best case."""
    c = range_coverage(mission, max_range_m, waveform, lever_arm_body_m, returns)
    fix = "to fix: " + c.remedy(mission)
    if c.in_range_pct < MOST_PCT or c.floor_reach_pct < MOST_PCT:
        raise ValueError(f"the floor and walls are mostly out of range: {c.describe()}; {fix}")
    if c.floor_reach_pct < FLOOR_WARN_PCT:
        return (f"part of the floor is out of range: {c.describe()}; where it is bare the report will "
                f"extrapolate it; {fix}")
    return None
