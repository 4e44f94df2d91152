"""Our Python autopilot: the paper's outer loops over rate/attitude inner loops and a quad-X mixer.

Outer loops (paper Sec. 3.2, Fig. 6):
- altitude: PID with a bias B, eq. (10)-(11), giving the collective thrust;
- heading: proportional on the error to the bearing of the next waypoint, eq. (12)-(14), saturated
  at the maximum yaw rate (the paper's psi_G in [-1, 1] scales that limit);
- speed via the pitch command, eq. (15)-(16): the desired speed is k D / |e_psi| capped at the
  mission speed, so the vehicle slows while it turns and when near a waypoint off its nose, and a
  PI on the forward speed turns it into a pitch angle;
- roll: the paper sets its roll gain phi_G to zero (no sideways flight is ever wanted). A quad
  with a roll angle of exactly zero keeps any sideways velocity it picks up when it yaws while
  moving, and with no drag to speak of it then orbits its waypoint; so the roll command here holds
  the sideways velocity at zero instead - still no sideways flight, now also no sideways drift.
Inner loops: attitude P -> body-rate PID -> mixer -> four ESC commands.

A pure controller in the rotorpy habit: `update(dt, state, target)` in, ESC commands out; it never
sees the simulator. Plain floats and the math module, because it runs at every physics step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

GRAVITY = 9.80665


def wrap_pi(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def clip(v: float, lo: float, hi: float) -> float:
    return lo if v < lo else hi if v > hi else v


@dataclass(frozen=True)
class Gains:
    """Controller gains (tuned on JSBSim's F450; see tests/sitl/vehicle/test_autopilot.py for the checks)."""

    # altitude, eq. (11): throttle per metre, per metre-second, per m/s; bias = hover throttle guess
    alt_kp: float = 0.12
    alt_ki: float = 0.05
    alt_kd: float = 0.18
    alt_i_limit: float = 0.25
    hover_throttle: float = 0.50
    # heading, eq. (14): yaw-rate command = clip(k e_psi, -1, 1) * max yaw rate
    heading_kp: float = 2.0
    # speed, eq. (15): desired speed = speed_k * D / |e_psi|, capped at the mission speed
    speed_k: float = 0.01
    vel_kp: float = 0.25
    vel_ki: float = 0.08
    vel_i_limit: float = 0.15
    lat_kp: float = 0.25
    max_tilt_rad: float = math.radians(20)
    # inner loops
    att_kp: float = 6.0
    rate_kp: float = 0.045
    rate_ki: float = 0.03
    rate_kd: float = 0.0012
    yaw_rate_kp: float = 0.12
    yaw_rate_ki: float = 0.05
    rate_i_limit: float = 0.1


@dataclass
class Target:
    """What the outer loops steer to: a point in NED, how fast, and how to point."""

    north_m: float
    east_m: float
    down_m: float
    speed_m_s: float = 0.0
    yaw_rad: float | None = None
    """Hold this heading (hover / turn in place); None: face the target (paper's heading law)."""
    climb_m_s: float = 0.0
    """How fast the target height itself rises (m/s, up): a climb's moving reference, fed forward so the vehicle
    climbs with it instead of lagging and winding up the integrator (0: a fixed height, the law of eq. (11))."""


class Autopilot:
    """Cascaded controller; call update() every physics step."""

    def __init__(self, gains: Gains | None = None, yaw_rate_max_rad_s: float = math.radians(30)) -> None:
        self.g = gains or Gains()
        self.yaw_rate_max_rad_s = yaw_rate_max_rad_s
        self.reset()

    def reset(self) -> None:
        self._i_alt = 0.0
        self._i_vel = 0.0
        self._i_rate = [0.0, 0.0, 0.0]
        self._prev_rate = [0.0, 0.0, 0.0]
        self.last_yaw_rate_cmd = 0.0
        self.last_speed_cmd = 0.0

    def update(self, dt: float, s: tuple[float, ...], t: Target) -> tuple[float, float, float, float]:
        """One control step. s = (n, e, d, vn, ve, vd, roll, pitch, yaw, p, q, r). Returns ESCs FR, AL, FL, AR."""
        g = self.g
        n, e, d, vn, ve, vd, roll, pitch, yaw, p, q, r = s
        # --- altitude, eq. (11), on height error; derivative on the measured climb rate
        e_z = (-t.down_m) - (-d)
        self._i_alt = clip(self._i_alt + e_z * dt, -g.alt_i_limit / g.alt_ki, g.alt_i_limit / g.alt_ki)
        thrust = g.hover_throttle + g.alt_kp * e_z + g.alt_ki * self._i_alt + g.alt_kd * (vd + t.climb_m_s)
        thrust /= max(0.5, math.cos(roll) * math.cos(pitch))
        # --- heading, eqs. (13)-(14)
        dn, de = t.north_m - n, t.east_m - e
        dist = math.hypot(dn, de)
        if t.yaw_rad is not None:
            e_psi = wrap_pi(t.yaw_rad - yaw)
        elif dist > 0.05:
            e_psi = wrap_pi(math.atan2(de, dn) - yaw)
        else:
            e_psi = 0.0
        yaw_rate_cmd = clip(g.heading_kp * e_psi, -1.0, 1.0) * self.yaw_rate_max_rad_s
        # --- speed via pitch, eqs. (15)-(16)
        u_fwd = vn * math.cos(yaw) + ve * math.sin(yaw)
        if t.yaw_rad is not None or t.speed_m_s <= 0.0:
            v_des = 0.0
        else:
            # Eq. (15) sets the speed; we fly it towards the target, not along the current heading,
            # and scale it by how well the nose points there. The paper's law alone keeps ~0.3 m/s
            # along the old heading through a corner, which at 6 deg/s (15 s for 90 deg) carries the
            # vehicle 3-4 m past the waypoint (through the wall at P_traj 5 %), and at 1 deg/s 12 m.
            v_des = min(t.speed_m_s, g.speed_k * dist / max(abs(e_psi), 1e-3)) * max(0.0, math.cos(e_psi))
        self.last_yaw_rate_cmd, self.last_speed_cmd = yaw_rate_cmd, v_des
        e_v = v_des * math.cos(e_psi) - u_fwd
        self._i_vel = clip(self._i_vel + e_v * dt, -g.vel_i_limit / g.vel_ki, g.vel_i_limit / g.vel_ki)
        pitch_cmd = -clip(g.vel_kp * e_v + g.vel_ki * self._i_vel, -g.max_tilt_rad, g.max_tilt_rad)
        v_lat = -vn * math.sin(yaw) + ve * math.cos(yaw)
        roll_cmd = clip(g.lat_kp * (v_des * math.sin(e_psi) - v_lat), -g.max_tilt_rad, g.max_tilt_rad)
        # --- attitude P -> rate PID
        rate_cmd = (g.att_kp * wrap_pi(roll_cmd - roll), g.att_kp * wrap_pi(pitch_cmd - pitch),
                    yaw_rate_cmd)
        # Body-rate PIDs, unrolled (roll and pitch with a derivative on the measurement, yaw without):
        # the same arithmetic in the same order as a loop over the axes, without its per-step overhead.
        i_rate, prev = self._i_rate, self._prev_rate
        kp, ki, kd, lim = g.rate_kp, g.rate_ki, g.rate_kd, g.rate_i_limit / g.rate_ki
        err = rate_cmd[0] - p
        i_rate[0] = clip(i_rate[0] + err * dt, -lim, lim)
        deriv = -(p - prev[0]) / dt
        prev[0] = p
        u_roll = kp * err + ki * i_rate[0] + kd * deriv
        err = rate_cmd[1] - q
        i_rate[1] = clip(i_rate[1] + err * dt, -lim, lim)
        deriv = -(q - prev[1]) / dt
        prev[1] = q
        u_pitch = kp * err + ki * i_rate[1] + kd * deriv
        ki = g.yaw_rate_ki
        lim = g.rate_i_limit / ki
        err = rate_cmd[2] - r
        i_rate[2] = clip(i_rate[2] + err * dt, -lim, lim)
        prev[2] = r
        u_yaw = g.yaw_rate_kp * err + ki * i_rate[2] + 0.0
        return mix(thrust, u_roll, u_pitch, u_yaw)


def mix(thrust: float, u_roll: float, u_pitch: float, u_yaw: float) -> tuple[float, float, float, float]:
    """Quad-X mixer for the F450's motor layout, checked against JSBSim's response.

    Positive u_roll rolls right (left motors up), u_pitch pitches nose up (front motors up),
    u_yaw yaws right (the FR/AL pair up).
    """
    fr = thrust - u_roll + u_pitch + u_yaw
    al = thrust + u_roll - u_pitch + u_yaw
    fl = thrust + u_roll + u_pitch - u_yaw
    ar = thrust - u_roll - u_pitch - u_yaw
    return (clip(fr, 0.0, 1.0), clip(al, 0.0, 1.0), clip(fl, 0.0, 1.0), clip(ar, 0.0, 1.0))
