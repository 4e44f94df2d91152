"""Telemetry streams: which messages are due when, and how each is encoded from the vehicle's state.

The schedule has no clock of its own: the server passes the time. In lockstep that is simulated
time, so runs are deterministic; `run_realtime` passes the wall clock, so a ground station gets
the rates it asked for in its own seconds whatever the speed-up (at 25x, simulated-time rates
would send it 25 times as many datagrams as it can read).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.core.geodesy import Home
from sitl.vehicle.api import VehicleState

TLOG_EPOCH_US = 1_704_067_200_000_000
"""2024-01-01T00:00:00Z: the wall-clock time of simulated t = 0 in logs and SYSTEM_TIME."""

STREAM_DEFAULT_HZ: dict[int, float] = {
    mavlink.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    mavlink.MAVLINK_MSG_ID_SYS_STATUS: 1.0,
    mavlink.MAVLINK_MSG_ID_SYSTEM_TIME: 1.0,
    mavlink.MAVLINK_MSG_ID_ATTITUDE: 50.0,
    mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 50.0,
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 5.0,
    mavlink.MAVLINK_MSG_ID_VFR_HUD: 4.0,
    mavlink.MAVLINK_MSG_ID_MISSION_CURRENT: 1.0,
    mavlink.MAVLINK_MSG_ID_HOME_POSITION: 0.0,
    mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN: 0.0,
}
"""Telemetry streams and their default rates (0 = off until asked for); SET_MESSAGE_INTERVAL changes them."""

_EPS_S = 1e-9


@dataclass
class _Stream:
    default_interval_s: float
    interval_s: float
    next_due_s: float = 0.0


def _interval(hz: float) -> float:
    return 1.0 / hz if hz > 0 else 0.0


class StreamSchedule:
    """When each stream is next due, in the seconds of whatever clock the caller times it by."""

    def __init__(self, rates_hz: dict[int, float] | None = None) -> None:
        rates = STREAM_DEFAULT_HZ if rates_hz is None else rates_hz
        self._streams = {mid: _Stream(_interval(hz), _interval(hz)) for mid, hz in rates.items()}
        self._next_any_due_s = 0.0  # earliest next_due_s of any stream (skip the scan until then)

    def __contains__(self, msg_id: int) -> bool:
        return msg_id in self._streams

    def may_be_due(self, now_s: float) -> bool:
        """False when `due(now_s)` would certainly return nothing (no stream is due yet)."""
        return now_s + _EPS_S >= self._next_any_due_s

    def due(self, now_s: float) -> list[int]:
        """The message ids due at now_s, in stream order; each is then scheduled one interval on.

        A stream that fell behind (updates rarer than its rate) restarts from now: no bursts.
        """
        if now_s + _EPS_S < self._next_any_due_s:
            return []  # nothing due: most physics steps (200 Hz physics, 50 Hz streams)
        due = []
        for msg_id, stream in self._streams.items():
            if stream.interval_s <= 0 or now_s + _EPS_S < stream.next_due_s:
                continue
            due.append(msg_id)
            stream.next_due_s += stream.interval_s
            if stream.next_due_s <= now_s + _EPS_S:
                stream.next_due_s = now_s + stream.interval_s
        nexts = [st.next_due_s for st in self._streams.values() if st.interval_s > 0]
        self._next_any_due_s = min(nexts) if nexts else math.inf
        return due

    def set_interval(self, msg_id: int, interval_us: float, now_s: float) -> None:
        """SET_MESSAGE_INTERVAL: 0 restores the default, -1 stops the stream; first message at now_s."""
        stream = self._streams[msg_id]
        if interval_us == 0:
            stream.interval_s = stream.default_interval_s
        elif interval_us == -1:
            stream.interval_s = 0.0
        elif math.isfinite(interval_us) and interval_us > 0:
            stream.interval_s = interval_us * 1e-6
        else:
            raise ValueError(f"interval {interval_us} us is invalid")
        stream.next_due_s = now_s
        self._next_any_due_s = -math.inf  # recompute at the next due()

    def interval_us(self, msg_id: int) -> int:
        """GET_MESSAGE_INTERVAL's answer: microseconds, or -1 for a stopped stream."""
        interval_s = self._streams[msg_id].interval_s
        return round(interval_s * 1e6) if interval_s > 0 else -1

    def reset(self, first_due_s: float) -> None:
        """Default rates again (an autopilot reboot), every stream first due at first_due_s."""
        for stream in self._streams.values():
            stream.interval_s = stream.default_interval_s
        self.restart(first_due_s)

    def restart(self, first_due_s: float) -> None:
        """Every stream next due at first_due_s, rates kept (the clock the schedule is timed by changed)."""
        for stream in self._streams.values():
            stream.next_due_s = first_due_s
        self._next_any_due_s = first_due_s


# ----- encoders ---------------------------------------------------------------------------------

def clamp_int(value: float, lo: int, hi: int) -> int:
    if not math.isfinite(value):
        return 0
    return max(lo, min(hi, round(value)))


def heading_cdeg(yaw_rad: float) -> int:
    """Heading 0..35999 centidegrees, as GLOBAL_POSITION_INT wants it."""
    return round(math.degrees(yaw_rad) * 100) % 36000 if math.isfinite(yaw_rad) else 0


_I32 = (-(2**31), 2**31 - 1)


def heartbeat(mav: Any, s: VehicleState) -> Any:
    base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if s.armed else 0)
    status = mavlink.MAV_STATE_ACTIVE if s.armed else mavlink.MAV_STATE_STANDBY
    return mav.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                base, int(s.mode), status, 3)


_S = mavlink
SENSORS_PRESENT = (_S.MAV_SYS_STATUS_SENSOR_3D_GYRO | _S.MAV_SYS_STATUS_SENSOR_3D_ACCEL
                   | _S.MAV_SYS_STATUS_SENSOR_3D_MAG | _S.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
                   | _S.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL | _S.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
                   | _S.MAV_SYS_STATUS_SENSOR_YAW_POSITION | _S.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
                   | _S.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL | _S.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
                   | _S.MAV_SYS_STATUS_AHRS | _S.MAV_SYS_STATUS_SENSOR_BATTERY)
"""What a simulated ArduCopter has (SYS_STATUS onboard_control_sensors_present): IMU, compass, baro,
its controllers, motors, AHRS, battery. No GPS (indoors), no geofence configured."""
SENSORS_HEALTHY_EXTRA = _S.MAV_SYS_STATUS_GEOFENCE
"""ArduPilot sets the geofence health bit whenever the fence is not breached, configured or not; a ground
station (MAVProxy) reads a clear bit as a breach."""


def sys_status(mav: Any, s: VehicleState, rx_errors: int) -> Any:
    """Present and healthy sensors as ArduCopter reports them; motor outputs enabled only when armed."""
    mv = clamp_int(s.battery_voltage_v * 1000, 0, 65535)
    enabled = SENSORS_PRESENT if s.armed else SENSORS_PRESENT & ~_S.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
    return mav.sys_status_encode(SENSORS_PRESENT, enabled, SENSORS_PRESENT | SENSORS_HEALTHY_EXTRA, 0, mv, -1, -1, 0,
                                 clamp_int(rx_errors, 0, 65535), 0, 0, 0, 0)


def system_time(mav: Any, s: VehicleState, boot_ms: int) -> Any:
    return mav.system_time_encode(TLOG_EPOCH_US + round(s.t_s * 1e6), boot_ms)


def attitude(mav: Any, s: VehicleState, boot_ms: int) -> Any:
    return mav.attitude_encode(boot_ms, s.roll_rad, s.pitch_rad, s.yaw_rad,
                               s.rollspeed_rad_s, s.pitchspeed_rad_s, s.yawspeed_rad_s)


def local_position(mav: Any, s: VehicleState, boot_ms: int) -> Any:
    return mav.local_position_ned_encode(boot_ms, *s.pos_ned_m, *s.vel_ned_m_s)


def global_position(mav: Any, s: VehicleState, boot_ms: int, home: Home) -> Any:
    n, e, d = s.pos_ned_m
    lat, lon = home.to_global(n, e)
    vel_cm = [clamp_int(v * 100, -32768, 32767) for v in s.vel_ned_m_s]
    return mav.global_position_int_encode(
        boot_ms, clamp_int(lat * 1e7, *_I32), clamp_int(lon * 1e7, *_I32),
        clamp_int((home.alt_m - d) * 1000, *_I32), clamp_int(-d * 1000, *_I32), *vel_cm, heading_cdeg(s.yaw_rad))


def vfr_hud(mav: Any, s: VehicleState, home: Home) -> Any:
    ground = math.hypot(s.vel_ned_m_s[0], s.vel_ned_m_s[1])
    return mav.vfr_hud_encode(ground, ground, heading_cdeg(s.yaw_rad) // 100, 50 if s.armed else 0,
                              home.alt_m - s.pos_ned_m[2], -s.vel_ned_m_s[2])


def gps_global_origin(mav: Any, origin: Home, t_s: float) -> Any:
    """GPS_GLOBAL_ORIGIN: the EKF origin (the SITL's autopilot has its home there)."""
    lat, lon, alt = origin_ints(origin)
    return mav.gps_global_origin_encode(lat, lon, alt, TLOG_EPOCH_US + round(t_s * 1e6))


def origin_ints(origin: Home) -> tuple[int, int, int]:
    """A position as MAVLink carries it: lat, lon in 1e-7 deg, altitude in mm."""
    return round(origin.lat_deg * 1e7), round(origin.lon_deg * 1e7), round(origin.alt_m * 1000)


def home_position(mav: Any, home: Home, t_s: float) -> Any:
    return mav.home_position_encode(
        round(home.lat_deg * 1e7), round(home.lon_deg * 1e7), round(home.alt_m * 1000),
        0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, TLOG_EPOCH_US + round(t_s * 1e6))
