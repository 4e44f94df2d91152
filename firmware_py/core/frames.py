"""Frames and the beam geometry of eqs. (3)-(6), vectorised.

Frames (docs/architecture.md, "Frames"):
- body B: FRD (x forward, y right, z down);
- local L: NED, as MAVLink LOCAL_POSITION_NED; attitude is ATTITUDE's ZYX Euler (roll, pitch, yaw);
- storage W: origin at a floor corner, x along the length, y along the width, z up.

The beam at servo angle gamma points along d_B = [0, sin gamma, cos gamma] (gamma = 0 straight
down, +90 deg to starboard): the sweep plane is perpendicular to forward flight (paper Fig. 1).
A real mounting is never exactly square (`Boresight`): the LiDAR sits on the servo horn tilted by
beta out of the sweep plane (the beam then sweeps a cone, leaning forward for beta > 0), and the
servo's axis is turned by psi about the body z axis (the sweep plane yawed):
d_B = Rz(psi) [sin beta, cos beta sin gamma, cos beta cos gamma].
A return at range r is  p_W = R_W<-NED (p_NED + R_NED<-B (r_B + r d_B)) + t_W,  the paper's
eqs. (3)-(6) with the lever arm made explicit. R_NED<-B = Rz(yaw) Ry(pitch) Rx(roll), the standard
aerospace ZYX sequence MAVLink uses (the paper's eq. (5) has a typo: the yaw matrix's last row is
[0 0 1]).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from firmware_py.core.numbers import is_finite_number


def rot_body_to_ned(roll_rad, pitch_rad, yaw_rad) -> np.ndarray:
    """R_NED<-B for ZYX Euler angles; inputs broadcast, output shape (..., 3, 3)."""
    cr, sr = np.cos(roll_rad), np.sin(roll_rad)
    cp, sp = np.cos(pitch_rad), np.sin(pitch_rad)
    cy, sy = np.cos(yaw_rad), np.sin(yaw_rad)
    cr, sr, cp, sp, cy, sy = np.broadcast_arrays(cr, sr, cp, sp, cy, sy)
    r = np.empty((*cr.shape, 3, 3))
    r[..., 0, 0] = cy * cp
    r[..., 0, 1] = cy * sp * sr - sy * cr
    r[..., 0, 2] = cy * sp * cr + sy * sr
    r[..., 1, 0] = sy * cp
    r[..., 1, 1] = sy * sp * sr + cy * cr
    r[..., 1, 2] = sy * sp * cr - cy * sr
    r[..., 2, 0] = -sp
    r[..., 2, 1] = cp * sr
    r[..., 2, 2] = cp * cr
    return r


def _rotate(r: np.ndarray, v: np.ndarray) -> np.ndarray:
    """r @ v for a (3, 3) rotation and vectors (..., 3).

    einsum, not `@`: a matmul over many points goes to a multithreaded BLAS whose spinning threads
    stall badly when several processes share a small CPU (seen: a 2-process sweep on 2 cores hung).
    """
    return np.einsum("ij,...j->...i", r, v)


def premultiply(r: np.ndarray, rs: np.ndarray) -> np.ndarray:
    """r @ rs[n] for a (3, 3) matrix and a stack (N, 3, 3): the beams' body-to-W rotations from their body-to-NED.

    Written out as three products, not einsum's generic loop (14 ms for 60,000 matrices against 8.5 ms; the
    same sums in the same order, so the same bits) nor `@` (see `_rotate`)."""
    return (r[None, :, 0, None] * rs[:, None, 0, :] + r[None, :, 1, None] * rs[:, None, 1, :]
            + r[None, :, 2, None] * rs[:, None, 2, :])


@dataclass(frozen=True)
class Boresight:
    """How the beam's mounting differs from square (module docstring), in rad.

    Attributes:
        tilt_rad: beta, the beam's tilt out of the sweep plane (> 0: leaning forward).
        sweep_yaw_rad: psi, the servo axis turned about body z (> 0: clockwise seen from above).
    """

    tilt_rad: float = 0.0
    sweep_yaw_rad: float = 0.0

    def __post_init__(self) -> None:
        for name in ("tilt_rad", "sweep_yaw_rad"):
            v = getattr(self, name)
            if not is_finite_number(v) or abs(v) > math.pi / 4:
                raise ValueError(f"boresight {name} must be a finite angle within +-45 deg, got {v!r}")

    @property
    def square(self) -> bool:
        return self.tilt_rad == 0.0 and self.sweep_yaw_rad == 0.0

    def to_dict(self) -> dict:
        return {"tilt_rad": self.tilt_rad, "sweep_yaw_rad": self.sweep_yaw_rad}

    @classmethod
    def from_dict(cls, d: dict) -> Boresight:
        return cls(float(d.get("tilt_rad", 0.0)), float(d.get("sweep_yaw_rad", 0.0)))


SQUARE = Boresight()


def beam_dir_body(servo_rad, boresight: Boresight = SQUARE) -> np.ndarray:
    """Unit beam direction in B for servo angle(s) gamma; shape (..., 3)."""
    g = np.asarray(servo_rad, dtype=float)
    if boresight.square:
        return np.stack([np.zeros_like(g), np.sin(g), np.cos(g)], axis=-1)
    cb, sb = math.cos(boresight.tilt_rad), math.sin(boresight.tilt_rad)
    cpsi, spsi = math.cos(boresight.sweep_yaw_rad), math.sin(boresight.sweep_yaw_rad)
    y0, z = cb * np.sin(g), cb * np.cos(g)
    return np.stack([cpsi * sb - spsi * y0, spsi * sb + cpsi * y0, z], axis=-1)


def beam_dot_body(m_xyz: np.ndarray, servo_rad, boresight: Boresight = SQUARE) -> np.ndarray:
    """m . `beam_dir_body`(servo_rad, boresight) per beam, m_xyz (3, ...) given component first, without forming the
    directions. Why: a fit of the mount evaluates every point's distance from its plane (m: the plane's normal in the
    body times the range) hundreds of times; the closed form costs a sine, a cosine and a few products per point
    instead of a stack and a contraction. Same geometry: the direction's components regrouped."""
    mx, my, mz = m_xyz
    g = np.asarray(servo_rad, dtype=float)
    if boresight.square:
        return my * np.sin(g) + mz * np.cos(g)
    cb, sb = math.cos(boresight.tilt_rad), math.sin(boresight.tilt_rad)
    cpsi, spsi = math.cos(boresight.sweep_yaw_rad), math.sin(boresight.sweep_yaw_rad)
    return sb * (cpsi * mx + spsi * my) + cb * ((cpsi * my - spsi * mx) * np.sin(g) + mz * np.cos(g))


def beam_dot_body_partials(m_xyz: np.ndarray, servo_rad,
                           boresight: Boresight = SQUARE) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The partial derivatives of `beam_dot_body` with respect to the servo angle, the tilt and the sweep yaw, per
    beam. Why: the mount's fit needs the Jacobian of every point's plane distance in its four parameters; in closed
    form it costs what one evaluation does, where finite differences cost one evaluation per parameter."""
    mx, my, mz = m_xyz
    g = np.asarray(servo_rad, dtype=float)
    cb, sb = math.cos(boresight.tilt_rad), math.sin(boresight.tilt_rad)
    cpsi, spsi = math.cos(boresight.sweep_yaw_rad), math.sin(boresight.sweep_yaw_rad)
    sg, cg = np.sin(g), np.cos(g)
    lateral = cpsi * my - spsi * mx  # m along the servo's swept axis
    in_plane = lateral * sg + mz * cg
    d_servo = cb * (lateral * cg - mz * sg)
    d_tilt = cb * (cpsi * mx + spsi * my) - sb * in_plane
    d_yaw = sb * (cpsi * my - spsi * mx) - cb * (spsi * my + cpsi * mx) * sg
    return d_servo, d_tilt, d_yaw


@dataclass(frozen=True)
class StorageFrame:
    """Placement of the storage frame W in the local NED frame.

    Attributes:
        origin_ned_m: the W origin (floor corner) in NED, m.
        heading_rad: heading of W's x axis (the building's length), clockwise from north.
    W's y axis is 90 deg to the left of x seen from above, so W is right-handed with z up.
    """

    origin_ned_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    heading_rad: float = 0.0

    def __post_init__(self) -> None:
        vals = [*self.origin_ned_m, self.heading_rad]
        if len(self.origin_ned_m) != 3 or not all(math.isfinite(v) for v in vals):
            raise ValueError(f"storage frame must be finite: origin {self.origin_ned_m}, "
                             f"heading {self.heading_rad}")

    @property
    def rot_w_from_ned(self) -> np.ndarray:
        c, s = math.cos(self.heading_rad), math.sin(self.heading_rad)
        return np.array([[c, s, 0.0], [s, -c, 0.0], [0.0, 0.0, -1.0]])

    def ned_to_w(self, p_ned: np.ndarray) -> np.ndarray:
        """Points (..., 3) from NED to W."""
        return _rotate(self.rot_w_from_ned, np.asarray(p_ned, dtype=float) - np.asarray(self.origin_ned_m))

    def w_to_ned(self, p_w: np.ndarray) -> np.ndarray:
        """Points (..., 3) from W to NED (the rotation is its own inverse: symmetric, orthonormal)."""
        return _rotate(self.rot_w_from_ned.T, np.asarray(p_w, dtype=float)) + np.asarray(self.origin_ned_m)

    def yaw_from_w_heading(self, course_w_rad):
        """NED yaw of a vehicle pointing along a W-frame direction atan2(dy, dx)."""
        return self.heading_rad - np.asarray(course_w_rad)

    def to_dict(self) -> dict:
        return {"origin_ned_m": list(self.origin_ned_m), "heading_rad": self.heading_rad}

    @classmethod
    def from_dict(cls, d: dict) -> StorageFrame:
        return cls(origin_ned_m=tuple(float(v) for v in d["origin_ned_m"]),
                   heading_rad=float(d["heading_rad"]))


def beam_rays_w(pos_ned_m: np.ndarray, roll_rad, pitch_rad, yaw_rad, servo_rad,
                lever_arm_body_m, frame: StorageFrame, boresight: Boresight = SQUARE) -> tuple[np.ndarray, np.ndarray]:
    """Origins and unit directions, in W, of beams fired from the given poses.

    Args:
        pos_ned_m: (N, 3) vehicle position in NED.
        roll_rad, pitch_rad, yaw_rad, servo_rad: (N,) angles.
        lever_arm_body_m: (3,) sensor position relative to the centre of gravity, in B.
        frame: the storage frame.
        boresight: the beam's mounting (square by default).
    Returns:
        (origins (N, 3), directions (N, 3)) in W.
    """
    origins, r_wb = beam_frames_w(pos_ned_m, roll_rad, pitch_rad, yaw_rad, lever_arm_body_m, frame)
    return origins, beam_dirs_w(r_wb, servo_rad, boresight)


def beam_frames_w(pos_ned_m: np.ndarray, roll_rad, pitch_rad, yaw_rad, lever_arm_body_m,
                  frame: StorageFrame) -> tuple[np.ndarray, np.ndarray]:
    """The part of `beam_rays_w` the pose fixes whatever the servo angle: the beams' origins in W (N, 3) and their
    body-to-W rotations (N, 3, 3). Why apart: a search for the servo's real timing places the same poses' beams at
    hundreds of other angles (`ground.pointcloud.PosedBeams`), and the rotations are most of the cost."""
    r_nb = rot_body_to_ned(roll_rad, pitch_rad, yaw_rad)
    r_wb = premultiply(frame.rot_w_from_ned, r_nb)
    origins = frame.ned_to_w(pos_ned_m) + np.einsum("nij,j->ni", r_wb, np.asarray(lever_arm_body_m, dtype=float))
    return origins, r_wb


def beam_dirs_w(r_wb: np.ndarray, servo_rad, boresight: Boresight = SQUARE) -> np.ndarray:
    """(N, 3) unit beam directions in W from the beams' body-to-W rotations (`beam_frames_w`) and servo angles."""
    return np.einsum("nij,nj->ni", r_wb, beam_dir_body(servo_rad, boresight))


def beam_ray_w(pos_ned_m, roll_rad: float, pitch_rad: float, yaw_rad: float, servo_rad: float,
               lever_arm_body_m, frame: StorageFrame,
               boresight: Boresight = SQUARE) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """One beam of `beam_rays_w`, in plain floats: the emulated LiDAR fires one ray per sample, where
    numpy's per-call overhead would cost more than the arithmetic (tests check both agree)."""
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
    r = ((cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr),
         (sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr),
         (-sp, cp * sr, cp * cr))
    lx, ly, lz = lever_arm_body_m
    lx, ly, lz = float(lx), float(ly), float(lz)
    sg, cg = math.sin(servo_rad), math.cos(servo_rad)
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = r
    pn, pe, pd = pos_ned_m
    fn, fe, fd = frame.origin_ned_m
    # Written out row by row (same operations, same order as a loop over rows): it runs 500 times a second.
    on = float(pn) + r00 * lx + r01 * ly + r02 * lz - fn
    oe = float(pe) + r10 * lx + r11 * ly + r12 * lz - fe
    od = float(pd) + r20 * lx + r21 * ly + r22 * lz - fd
    if boresight.square:
        dn, de, dd = r01 * sg + r02 * cg, r11 * sg + r12 * cg, r21 * sg + r22 * cg
    else:  # `beam_dir_body`'s tilted beam, in floats (numpy's stack of three scalars cost 30 us a sample)
        cb, sb = math.cos(boresight.tilt_rad), math.sin(boresight.tilt_rad)
        cpsi, spsi = math.cos(boresight.sweep_yaw_rad), math.sin(boresight.sweep_yaw_rad)
        y0 = cb * sg
        bx, by, bz = cpsi * sb - spsi * y0, spsi * sb + cpsi * y0, cb * cg
        dn, de, dd = r00 * bx + r01 * by + r02 * bz, r10 * bx + r11 * by + r12 * bz, r20 * bx + r21 * by + r22 * bz
    c, s = math.cos(frame.heading_rad), math.sin(frame.heading_rad)  # rot_w_from_ned, written out
    return ((c * on + s * oe, s * on - c * oe, -od),
            (c * dn + s * de, s * dn - c * de, -dd))


def points_w(pos_ned_m, roll_rad, pitch_rad, yaw_rad, servo_rad, range_m, lever_arm_body_m,
             frame: StorageFrame, boresight: Boresight = SQUARE) -> np.ndarray:
    """Eqs. (3)-(6): the (N, 3) points in W hit by beams of the given ranges."""
    origins, dirs = beam_rays_w(pos_ned_m, roll_rad, pitch_rad, yaw_rad, servo_rad, lever_arm_body_m,
                                frame, boresight)
    return origins + dirs * np.asarray(range_m, dtype=float)[:, None]
