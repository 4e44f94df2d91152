"""Survey missions: the paper's rectangle (Fig. 7, eqs. 17-18) with one- or two-step corners (Fig. 15).

Waypoints are in the storage frame W (x along the length, y along the width). The rectangle's
corners sit T_L = P_traj L and T_W = P_traj W in from the walls and are flown counter-clockwise
seen from above. Two-step corners replace each corner C by two waypoints a cut distance before and
after C on the two legs, so the vehicle turns twice by 45 deg; the paper cut at 10 % of W (Fig. 15
caption).

The waypoints form a closed loop W0 ... Wn = W0. The vehicle arrives on W0 along the closing leg
(as it would after flying in from take-off), turns there towards W1 and flies the loop back to W0:
every waypoint is turned at exactly once, so no corner of the building is favoured or left out.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass, field

import numpy as np

from firmware_py.core.config_file import MIN_YAW_RATE_DEG_S
from firmware_py.core.storage import Storage

TURN_MODES = ("one-step", "two-step")
MIN_LEG_M = 1.0
"""The shortest leg a rectangle may have: about twice a small multirotor's span. P_traj near 50 % shrinks the
loop to a point (49.99999 % flew a loop of 0 m); the paper's P_traj of 5-30 % gives legs of 16 m or more."""


@dataclass(frozen=True)
class Mission:
    """A rectangular survey.

    Attributes:
        storage: the building.
        p_traj: waypoint offset from the walls as a fraction of L and W (paper: 0.05-0.30).
        turn: 'one-step' (90 deg turns) or 'two-step' (two 45 deg turns per corner).
        speed_m_s: ground speed on the legs.
        altitude_m: flight height above the floor.
        yaw_rate_max_rad_s: yaw-rate limit in the turns.
        two_step_cut_m: distance from a corner at which a two-step turn starts; None = 10 % of W.
        min_clearance_m: the least distance the vehicle keeps from walls and roof.
    """

    storage: Storage = field(default_factory=Storage)
    p_traj: float = 0.05
    turn: str = "one-step"
    speed_m_s: float = 1.0
    altitude_m: float = 12.0
    yaw_rate_max_rad_s: float = math.radians(30.0)
    two_step_cut_m: float | None = None
    min_clearance_m: float = 0.5

    def __post_init__(self) -> None:
        s = self.storage
        if not (math.isfinite(self.p_traj) and 0.0 < self.p_traj < 0.5):
            raise ValueError(f"P_traj must be between 0 and 50 % (exclusive), got {self.p_traj * 100:g} %")
        if self.turn not in TURN_MODES:
            raise ValueError(f"turn must be one of {', '.join(TURN_MODES)}, got {self.turn!r}")
        if not (math.isfinite(self.speed_m_s) and 0.05 <= self.speed_m_s <= 15.0):
            raise ValueError(f"speed must be 0.05-15 m/s, got {self.speed_m_s}")
        if not (math.isfinite(self.yaw_rate_max_rad_s)
                and math.radians(MIN_YAW_RATE_DEG_S) <= self.yaw_rate_max_rad_s <= 2 * math.pi):
            raise ValueError(f"max yaw rate must be in [{MIN_YAW_RATE_DEG_S:g}, 360] deg/s, got "
                             f"{math.degrees(self.yaw_rate_max_rad_s):g} deg/s")
        if not (math.isfinite(self.min_clearance_m) and self.min_clearance_m >= 0):
            raise ValueError(f"clearance must be >= 0 m, got {self.min_clearance_m}")
        if not (math.isfinite(self.altitude_m)
                and self.min_clearance_m < self.altitude_m <= s.height_m - self.min_clearance_m):
            raise ValueError(f"altitude {self.altitude_m:g} m does not fit the {s} building "
                             f"(needs {self.min_clearance_m:g} m clearance to floor and roof)")
        gap = min(self.p_traj * s.length_m, self.p_traj * s.width_m)
        if gap < self.min_clearance_m:
            raise ValueError(f"P_traj {self.p_traj * 100:g} % puts the flight {gap:.2f} m from a wall of the "
                             f"{s} building; it needs at least {self.min_clearance_m:g} m")
        shortest = (1 - 2 * self.p_traj) * min(s.length_m, s.width_m)
        if shortest < MIN_LEG_M:
            most = 50.0 * (1 - MIN_LEG_M / min(s.length_m, s.width_m))
            raise ValueError(f"P_traj {self.p_traj * 100:.7g} % leaves a loop whose shorter legs are {shortest:.2f} m "
                             f"in the {s} building: at most {most:.1f} % gives legs of {MIN_LEG_M:g} m or more")
        if self.turn == "two-step":
            cut = self.cut_m
            if not (math.isfinite(cut) and 0 < cut < shortest / 2):
                raise ValueError(f"two-step cut {cut:g} m must be > 0 and below half the shortest leg "
                                 f"({shortest / 2:.2f} m)")

    @property
    def cut_m(self) -> float:
        return 0.1 * self.storage.width_m if self.two_step_cut_m is None else float(self.two_step_cut_m)

    def corners_w(self) -> np.ndarray:
        """The four rectangle corners (4, 2) in W, in flight order (eqs. 17-18)."""
        s = self.storage
        tl, tw = self.p_traj * s.length_m, self.p_traj * s.width_m
        return np.array([[tl, tw], [s.length_m - tl, tw], [s.length_m - tl, s.width_m - tw],
                         [tl, s.width_m - tw]])

    def waypoints_w(self) -> np.ndarray:
        """Waypoints (K, 2) in W, first == last (the closed loop)."""
        c = self.corners_w()
        if self.turn == "one-step":
            return np.vstack([c, c[:1]])
        pts = []
        for i in range(4):
            u_in = _unit(c[i] - c[i - 1])
            u_out = _unit(c[(i + 1) % 4] - c[i])
            pts += [c[i] - self.cut_m * u_in, c[i] + self.cut_m * u_out]
        return np.vstack([pts, pts[:1]])

    def path_length_m(self) -> float:
        return float(np.linalg.norm(np.diff(self.waypoints_w(), axis=0), axis=1).sum())

    def to_dict(self) -> dict:
        d = asdict(self)
        d["storage"] = self.storage.to_dict()
        d["two_step_cut_m"] = self.cut_m if self.turn == "two-step" else None
        return d

    @classmethod
    def from_dict(cls, d: dict) -> Mission:
        d = dict(d)
        d["storage"] = Storage.from_dict(d["storage"])
        return cls(**d)

    @property
    def mission_id(self) -> str:
        """Short stable hash of the mission parameters (ties logs, truth and reports together)."""
        blob = json.dumps(self.to_dict(), sort_keys=True).encode()
        return hashlib.sha256(blob).hexdigest()[:12]


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)
