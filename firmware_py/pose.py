"""Vehicle pose at any companion time: LOCAL_POSITION_NED and ATTITUDE interpolated by their own stamps.

The autopilot sends the two messages separately, each stamped with its own `time_boot_ms` (ArduPilot
stamps at send time). The caller maps each stamp to companion time (TimesyncEstimator) and adds it
here; `pose_at(t_ns)` interpolates each stream between its own two samples bracketing t: position
linearly, attitude by quaternion slerp (a short pure-math slerp: this runs per LiDAR sample, 500 Hz on
a Raspberry Pi). Samples are kept in time order whatever order they arrive in, so a pose is never
paired by receive order.

A pose is STALE (and its values NaN, so an old pose can never tag a sample) when a bracketing sample
is more than max_age_ns from t, when t is before the oldest sample, or when t is past the newest by
more than extrapolate_ns (up to that, the last two samples are extrapolated: the payload tags
samples close to "now", and the newest pose is a link latency old). It is MISSING when a stream has
no samples at all; `status()` says why, including the indoor case where the EKF has no origin.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.core.samplelog import SampleFlags

_NAN = float("nan")
_NAN3 = (_NAN, _NAN, _NAN)

NO_POSITION_STATUS = (
    "no LOCAL_POSITION_NED from the autopilot yet: it has no local position estimate. Indoors, without "
    "GPS, the EKF needs an origin before it publishes one: send SET_GPS_GLOBAL_ORIGIN "
    "(firmware_py.pose.set_gps_global_origin_msg) and check its position source (optical flow, beacons, "
    "external navigation)"
)


@dataclass(frozen=True, slots=True)
class PoseSample:
    """The vehicle's pose at companion time t_ns (NED position, ZYX Euler attitude): what a pose
    source hands the payload loop, typed so nothing there is probed with getattr.

    Values are NaN when stale or missing (missing implies stale). age_s is the time from t to the
    farther bracketing sample (inf when missing).
    """

    t_ns: int
    pos_ned_m: tuple[float, float, float]
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    age_s: float
    stale: bool
    missing: bool

    @property
    def usable(self) -> bool:
        return not (self.stale or self.missing)

    @property
    def flags(self) -> SampleFlags:
        """The sample-log flags this pose puts on a LiDAR sample it tags."""
        if self.missing:
            return SampleFlags.NO_POSE
        return SampleFlags.STALE_POSE if self.stale else SampleFlags.NONE


# ----- quaternion math (w, x, y, z), ZYX Euler as MAVLink ATTITUDE ---------------------------------

Quat = tuple[float, float, float, float]


def quat_from_euler(roll_rad: float, pitch_rad: float, yaw_rad: float) -> Quat:
    """Unit quaternion of R = Rz(yaw) Ry(pitch) Rx(roll) (body FRD to NED)."""
    cr, sr = math.cos(0.5 * roll_rad), math.sin(0.5 * roll_rad)
    cp, sp = math.cos(0.5 * pitch_rad), math.sin(0.5 * pitch_rad)
    cy, sy = math.cos(0.5 * yaw_rad), math.sin(0.5 * yaw_rad)
    return (cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy)


def euler_from_quat(q: Quat) -> tuple[float, float, float]:
    """(roll, pitch, yaw) in rad of a unit quaternion; pitch clamped at +-90 deg."""
    w, x, y, z = q
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    s = 2.0 * (w * y - z * x)
    pitch = math.asin(1.0 if s > 1.0 else -1.0 if s < -1.0 else s)
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw


def slerp(q0: Quat, q1: Quat, u: float) -> Quat:
    """Spherical interpolation along the shorter arc; u in [0, 1] interpolates, u > 1 extrapolates."""
    w0, x0, y0, z0 = q0
    w1, x1, y1, z1 = q1
    d = w0 * w1 + x0 * x1 + y0 * y1 + z0 * z1
    if d < 0.0:  # q and -q are the same rotation: take the short way round
        w1, x1, y1, z1, d = -w1, -x1, -y1, -z1, -d
    if d > 0.9999999:  # within ~0.05 deg: lerp is exact to ~1e-10 rad and avoids dividing by sin(~0)
        a, b = 1.0 - u, u
    else:
        theta = math.acos(d)
        s = math.sin(theta)
        a, b = math.sin((1.0 - u) * theta) / s, math.sin(u * theta) / s
    w, x, y, z = a * w0 + b * w1, a * x0 + b * x1, a * y0 + b * y1, a * z0 + b * z1
    n = 1.0 / math.sqrt(w * w + x * x + y * y + z * z)
    return w * n, x * n, y * n, z * n


# ----- the buffer -----------------------------------------------------------------------------------

class PoseBuffer:
    """Time-ordered position and attitude samples (companion ns) and their interpolation."""

    def __init__(self, capacity: int = 256, max_age_ns: int = 100_000_000, extrapolate_ns: int = 25_000_000) -> None:
        if not (isinstance(capacity, int) and capacity >= 2):
            raise ValueError(f"capacity must be an integer >= 2, got {capacity!r}")
        if not (isinstance(max_age_ns, int) and max_age_ns > 0):
            raise ValueError(f"max_age_ns must be an integer > 0, got {max_age_ns!r}")
        if not (isinstance(extrapolate_ns, int) and 0 <= extrapolate_ns <= max_age_ns):
            raise ValueError(f"extrapolate_ns must be an integer in 0..max_age_ns, got {extrapolate_ns!r}")
        self.capacity, self.max_age_ns, self.extrapolate_ns = capacity, max_age_ns, extrapolate_ns
        self._pos_t: list[int] = []
        self._pos: list[tuple[float, float, float]] = []
        self._att_t: list[int] = []
        self._att: list[Quat] = []
        self.ever_position = False
        self.ever_attitude = False
        self.stats: dict[str, int] = {"positions": 0, "attitudes": 0, "rejected_nonfinite": 0,
                                      "out_of_order": 0, "duplicates": 0, "clears": 0}

    # ----- ingest -------------------------------------------------------------------------------

    def add_position(self, t_ns: int, pos_ned_m: Sequence[float]) -> bool:
        """Add a LOCAL_POSITION_NED position (m, NED) at companion time t_ns; False if not finite."""
        p = tuple(float(v) for v in pos_ned_m)
        if len(p) != 3 or not all(math.isfinite(v) for v in p):
            self.stats["rejected_nonfinite"] += 1
            return False
        self._insert(self._pos_t, self._pos, int(t_ns), p)
        self.ever_position = True
        self.stats["positions"] += 1
        return True

    def add_attitude(self, t_ns: int, roll_rad: float, pitch_rad: float, yaw_rad: float) -> bool:
        """Add an ATTITUDE (ZYX Euler, rad) at companion time t_ns; False if not finite."""
        if not (math.isfinite(roll_rad) and math.isfinite(pitch_rad) and math.isfinite(yaw_rad)):
            self.stats["rejected_nonfinite"] += 1
            return False
        self._insert(self._att_t, self._att, int(t_ns), quat_from_euler(roll_rad, pitch_rad, yaw_rad))
        self.ever_attitude = True
        self.stats["attitudes"] += 1
        return True

    def clear(self) -> None:
        """Drop every sample (after a time-sync reset their companion times are no longer trustworthy)."""
        self._pos_t.clear()
        self._pos.clear()
        self._att_t.clear()
        self._att.clear()
        self.stats["clears"] += 1

    def _insert(self, ts: list[int], vals: list[Any], t: int, v: Any) -> None:
        if not ts or t > ts[-1]:
            ts.append(t)
            vals.append(v)
        else:
            i = bisect_right(ts, t)
            if i and ts[i - 1] == t:
                vals[i - 1] = v  # the same stamp again: keep the newer copy
                self.stats["duplicates"] += 1
                return
            self.stats["out_of_order"] += 1
            ts.insert(i, t)
            vals.insert(i, v)
        if len(ts) > self.capacity:
            del ts[0]
            del vals[0]

    # ----- query --------------------------------------------------------------------------------

    @property
    def newest_ns(self) -> int | None:
        """Companion time of the older of the two streams' newest samples (what a pose can rely on)."""
        if not self._pos_t or not self._att_t:
            return None
        return min(self._pos_t[-1], self._att_t[-1])

    def __len__(self) -> int:
        return min(len(self._pos_t), len(self._att_t))

    def pose_at(self, t_ns: int) -> PoseSample:
        """The pose at companion time t_ns (never None: its flags say when it cannot be used)."""
        t = int(t_ns)
        if not self._pos_t or not self._att_t:
            return PoseSample(t, _NAN3, _NAN, _NAN, _NAN, math.inf, stale=True, missing=True)
        p = self._bracket(self._pos_t, t)
        a = self._bracket(self._att_t, t)
        age_s = max(p[3], a[3]) / 1e9
        if not (p[4] and a[4]):
            return PoseSample(t, _NAN3, _NAN, _NAN, _NAN, age_s, stale=True, missing=False)
        i0, i1, u = p[0], p[1], p[2]
        p0, p1 = self._pos[i0], self._pos[i1]
        pos = (p0[0] + u * (p1[0] - p0[0]), p0[1] + u * (p1[1] - p0[1]), p0[2] + u * (p1[2] - p0[2]))
        roll, pitch, yaw = euler_from_quat(slerp(self._att[a[0]], self._att[a[1]], a[2]))
        return PoseSample(t, pos, roll, pitch, yaw, age_s, stale=False, missing=False)

    def _bracket(self, ts: list[int], t: int) -> tuple[int, int, float, int, bool]:
        """(i0, i1, u, age_ns, ok) for time t in one stream: value = v[i0] + u (v[i1] - v[i0])."""
        n = len(ts)
        i = bisect_right(ts, t)
        if i == 0:  # before the oldest sample: never extrapolate backwards
            return 0, 0, 0.0, ts[0] - t, False
        if i == n:  # at or past the newest sample
            ahead = t - ts[-1]
            if n == 1:
                return 0, 0, 0.0, ahead, ahead <= self.extrapolate_ns
            i0, i1 = n - 2, n - 1
            age = t - ts[i0]
            ok = ahead <= self.extrapolate_ns and age <= self.max_age_ns
            return i0, i1, (t - ts[i0]) / (ts[i1] - ts[i0]), age, ok
        i0, i1 = i - 1, i
        age = max(t - ts[i0], ts[i1] - t)
        return i0, i1, (t - ts[i0]) / (ts[i1] - ts[i0]), age, age <= self.max_age_ns

    def status(self) -> str:
        """One line for the operator: what is missing and why, or what the buffer holds."""
        if not self.ever_position:
            return NO_POSITION_STATUS
        if not self.ever_attitude:
            return "no ATTITUDE from the autopilot yet (is the stream requested? see MAV_CMD_SET_MESSAGE_INTERVAL)"
        if not self._pos_t or not self._att_t:
            return "pose buffer empty: cleared after a time-sync reset, waiting for new samples"
        return (f"ok: {len(self._pos_t)} positions, {len(self._att_t)} attitudes, "
                f"spanning {(self.newest_ns - max(self._pos_t[0], self._att_t[0])) / 1e9:.2f} s")


def set_gps_global_origin_msg(lat_deg: float, lon_deg: float, alt_m: float, target_system: int = 1) -> Any:
    """SET_GPS_GLOBAL_ORIGIN for an indoor EKF: the local NED origin's latitude, longitude (deg) and
    altitude (m, MSL). ArduPilot publishes LOCAL_POSITION_NED only once its EKF has an origin."""
    if not (math.isfinite(lat_deg) and -90.0 <= lat_deg <= 90.0):
        raise ValueError(f"latitude must be within -90..90 deg, got {lat_deg}")
    if not (math.isfinite(lon_deg) and -180.0 <= lon_deg <= 180.0):
        raise ValueError(f"longitude must be within -180..180 deg, got {lon_deg}")
    if not (math.isfinite(alt_m) and -1000.0 <= alt_m <= 100_000.0):
        raise ValueError(f"altitude must be within -1000..100000 m, got {alt_m}")
    if not (isinstance(target_system, int) and 1 <= target_system <= 255):
        raise ValueError(f"target_system must be an integer 1-255, got {target_system!r}")
    return mavlink.MAVLink_set_gps_global_origin_message(
        target_system, round(lat_deg * 1e7), round(lon_deg * 1e7), round(alt_m * 1000.0), 0)
