"""Ideal plant: a kinematic vehicle that flies the mission exactly.

Constant speed on the legs, level attitude, and turns in place at the yaw-rate limit at each
waypoint, including the first (arrived at along the closing leg, see sitl.missions.rectangle). It is the
reference against which the flight-dynamics plant is judged, and the fast path for sweeps.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from firmware_py.core.frames import StorageFrame
from sitl.missions.rectangle import Mission


def wrap_pi(a):
    """Angle(s) wrapped to [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


@dataclass(frozen=True)
class Trajectory:
    """Vehicle states at sample times: position in NED (N, 3), attitude (N,) each, rad."""

    t_s: np.ndarray
    pos_ned_m: np.ndarray
    roll_rad: np.ndarray
    pitch_rad: np.ndarray
    yaw_rad: np.ndarray

    def __len__(self) -> int:
        return len(self.t_s)


class IdealPlant:
    """Piecewise kinematic flight of a Mission: legs at speed, turns at the yaw-rate limit."""

    def __init__(self, mission: Mission, frame: StorageFrame) -> None:
        self.mission = mission
        self.frame = frame
        wp = mission.waypoints_w()
        d = np.diff(wp, axis=0)
        self._leg_len = np.linalg.norm(d, axis=1)
        course_w = np.arctan2(d[:, 1], d[:, 0])
        self._yaw_leg = wrap_pi(frame.yaw_from_w_heading(course_w))
        # turns[i] is the signed (shortest way) turn onto leg i, made on waypoint i; turn 0 is from the
        # closing leg's heading, the way the vehicle arrives on the loop.
        turns = wrap_pi(np.diff(np.r_[self._yaw_leg[-1], self._yaw_leg]))
        self._yaw_before = self._yaw_leg - turns
        # Segment table: before each leg, the turn onto it.
        starts, kinds, idx = [0.0], [], []
        t = 0.0
        for i, length in enumerate(self._leg_len):
            kinds.append("turn"), idx.append(i)
            t += abs(turns[i]) / mission.yaw_rate_max_rad_s
            starts.append(t)
            kinds.append("leg"), idx.append(i)
            t += length / mission.speed_m_s
            starts.append(t)
        self._seg_start = np.array(starts)
        self._seg_kind = np.array([k == "turn" for k in kinds])
        self._seg_idx = np.array(idx)
        self._turns = turns
        self._wp = wp
        self.duration_s = t

    def states(self, t_s: np.ndarray) -> Trajectory:
        """Exact states at times t_s (clipped to [0, duration])."""
        m = self.mission
        t = np.clip(np.asarray(t_s, dtype=float), 0.0, self.duration_s)
        seg = np.clip(np.searchsorted(self._seg_start, t, side="right") - 1, 0, len(self._seg_kind) - 1)
        tau = t - self._seg_start[seg]
        is_turn = self._seg_kind[seg]
        i = self._seg_idx[seg]
        # Leg i: move from waypoint i towards i+1.  Turn i: sit on waypoint i, rotating onto leg i.
        frac = np.where(is_turn, 0.0, np.minimum(tau * m.speed_m_s / self._leg_len[i], 1.0))
        xy = self._wp[i] + (self._wp[i + 1] - self._wp[i]) * frac[:, None]
        turned = np.sign(self._turns[i]) * np.minimum(tau * m.yaw_rate_max_rad_s, np.abs(self._turns[i]))
        yaw = np.where(is_turn, self._yaw_before[i] + turned, self._yaw_leg[i])
        p_w = np.column_stack([xy, np.full(len(t), m.altitude_m)])
        zeros = np.zeros(len(t))
        return Trajectory(t, self.frame.w_to_ned(p_w), zeros, zeros.copy(), wrap_pi(yaw))

    def sample_times(self, rate_hz: float) -> np.ndarray:
        """Times of a sensor sampling at rate_hz over the whole mission."""
        n = int(np.floor(self.duration_s * rate_hz)) + 1
        return np.arange(n) / rate_hz
