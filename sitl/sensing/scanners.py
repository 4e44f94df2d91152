"""The paper's comparison sensors (Sec. 4.5): a 2D and a 3D scanning LiDAR, simulated in chunks.

Beam conventions, in the body frame B (FRD), extending the 1D's d_B = [0, sin gamma, cos gamma]:

- phi, the scan angle in the body y-z plane: 0 = straight down, +90 deg = starboard, +-180 deg = up.
- omega, a channel's elevation out of that plane: + = forward.
- d_B = [sin omega, cos omega sin phi, cos omega cos phi]; the 2D has the single channel omega = 0.

2D (Hokuyo UTM-30LX): scan plane = body y-z (perpendicular to the flight), its 270 deg sector
centred straight down, so the blind 90 deg points at the roof. Its mirror turns at 40 Hz; in each
revolution of 1440 steps of 0.25 deg it fires on the sector's 1081 steps, phi = -135 deg + 0.25 deg k
(k = 0..1080), port to starboard.

3D (Velodyne Puck LITE): mounted with its rotation axis along body x (forward). Each channel then
sweeps a full circle in (nearly) the plane perpendicular to the flight, the 16 channels fanned
+-15 deg fore and aft: the sensor sees floor, pile, walls and roof across the whole building at
every instant. (A vertical axis, the usual car mounting, would sweep a horizontal +-15 deg band
that only reaches the walls from a drone at 12 m.) It turns at 10 Hz; at each of 1800 azimuth steps
of 0.2 deg per revolution (phi = 0.2 deg s) the 16 channels fire one after the other.

Timing: every beam has a slot on one integer grid, slot k at t = k / R (R = slot_rate_hz, the
rotation rate x steps per revolution x channels). A time interval [t0, t1) owns the slots
ceil(t0 R) .. ceil(t1 R) - 1 (boundaries first rounded to the grid), so consecutive chunks never
double-count or skip a beam, and `beam_dirs_body` recovers the slot (hence step and channel) from
the time alone.

Ranges are ideal (float32 ray tracing, micrometres) unless a generator is given, which adds
normal range noise of the datasheet's sigma. No quantisation: both sensors resolve a few mm, far
below their +-3 cm accuracy.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from firmware_py.core.frames import StorageFrame, premultiply, rot_body_to_ned
from sitl.vehicle.ideal_plant import Trajectory
from sitl.world.raycast import World


@dataclass(frozen=True)
class ScannerSpec:
    """A spinning LiDAR: a scan plane (body y-z) swept at rotation_hz, with channels fanned out of it.

    Attributes:
        name: model.
        payload_kg: sensor mass the drone carries.
        max_range_m: no return beyond this range.
        range_sigma_m: 1-sigma range error (noise model and the ground station's wall tolerance).
        rotation_hz: revolutions (scans) per second.
        step_deg: angular step between firings within a revolution; must divide 360 deg.
        fov_deg: the scanned sector of the revolution, centred straight down (360 = all round);
            a sector includes both ends.
        channel_elevations_deg: out-of-plane angle of each channel, + forward; all fire at each step.
    """

    name: str
    payload_kg: float
    max_range_m: float
    range_sigma_m: float
    rotation_hz: float
    step_deg: float
    fov_deg: float
    channel_elevations_deg: tuple[float, ...] = (0.0,)

    def __post_init__(self) -> None:
        for k in ("payload_kg", "max_range_m", "rotation_hz", "step_deg", "fov_deg"):
            v = getattr(self, k)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"scanner {k} must be > 0, got {v}")
        if not (math.isfinite(self.range_sigma_m) and self.range_sigma_m >= 0):
            raise ValueError(f"scanner range sigma must be >= 0 m, got {self.range_sigma_m}")
        if abs(360.0 / self.step_deg - round(360.0 / self.step_deg)) > 1e-9:
            raise ValueError(f"scanner step {self.step_deg} deg must divide 360 deg")
        if self.fov_deg > 360.0:
            raise ValueError(f"scanner field of view must be <= 360 deg, got {self.fov_deg}")
        if not self.channel_elevations_deg or not all(abs(e) < 90 for e in self.channel_elevations_deg):
            raise ValueError(f"channel elevations must be within +-90 deg, got {self.channel_elevations_deg}")

    @property
    def steps_per_rev(self) -> int:
        return round(360.0 / self.step_deg)

    @property
    def sector_steps(self) -> int:
        """Steps fired per revolution per channel: the sector and both its ends, or all round."""
        if self.fov_deg >= 360.0:
            return self.steps_per_rev
        return min(self.steps_per_rev, math.floor(self.fov_deg / self.step_deg + 1e-9) + 1)

    @property
    def n_channels(self) -> int:
        return len(self.channel_elevations_deg)

    @property
    def slot_rate_hz(self) -> float:
        """Beam slots per second, fired or not (the blind sector has slots too)."""
        return self.rotation_hz * self.steps_per_rev * self.n_channels

    @property
    def points_per_s(self) -> float:
        """Beams fired per second."""
        return self.rotation_hz * self.sector_steps * self.n_channels

    @property
    def first_angle_rad(self) -> float:
        """phi of step 0: the sector's port end (or straight down for a full circle)."""
        return 0.0 if self.fov_deg >= 360.0 else -math.radians(self.step_deg * (self.sector_steps - 1) / 2)


HOKUYO_UTM_30LX = ScannerSpec(
    name="Hokuyo UTM-30LX", payload_kg=0.370, max_range_m=30.0, range_sigma_m=0.03,
    rotation_hz=40.0, step_deg=0.25, fov_deg=270.0)
"""2D LiDAR of the paper (Sec. 4.5) and its datasheet: 270 deg field of view at 0.25 deg steps,
25 ms per scan (40 Hz), 30 m range, 370 g; accuracy +-30 mm to 10 m (+-50 mm to 30 m), taken as
a 3 cm 1-sigma. The sector's 1081 steps (both ends) give 43,240 points/s; the paper's 43,200 is
40 x 1080."""

VELODYNE_PUCK_LITE = ScannerSpec(
    name="Velodyne Puck LITE", payload_kg=0.830, max_range_m=100.0, range_sigma_m=0.03,
    rotation_hz=10.0, step_deg=0.2, fov_deg=360.0,
    channel_elevations_deg=tuple(float(e) for e in range(-15, 16, 2)))
"""3D LiDAR of the paper (Sec. 4.5) and its datasheet: 16 channels 2 deg apart over +-15 deg,
360 deg at 0.2 deg azimuth steps at 10 Hz (16 x 1800 x 10 = 288,000 points/s; ~300,000 quoted),
100 m range, 830 g, +-3 cm accuracy (taken as 1 sigma). Mounted with its axis along body x (see
the module docstring)."""


@dataclass(frozen=True)
class ScanChunk:
    """The returns of the beams fired in [t0_s, t1_s); no-return beams are dropped.

    Attributes:
        points_w: (n, 3) hit points in W.
        range_m: (n,) ranges (noisy when scanned with a generator).
        dirs_w: (n, 3) unit beam directions in W (the wall tolerance projects the range error on them).
        t_s: (n,) firing times of the returns.
        path_w: (m, 3) sensor positions in W once per revolution, the flown path for plots.
        n_beams: beams fired in the interval, returns or not.
    """

    t0_s: float
    t1_s: float
    points_w: np.ndarray
    range_m: np.ndarray
    dirs_w: np.ndarray
    t_s: np.ndarray
    path_w: np.ndarray
    n_beams: int

    def __len__(self) -> int:
        return len(self.range_m)


SLOT_EPS = 1e-6


def _fire_slots(spec: ScannerSpec, t0_s: float, t1_s: float) -> np.ndarray:
    """Slot indices (int64) of the beams fired in [t0_s, t1_s)."""
    rate = spec.slot_rate_hz
    # A boundary within a millionth of a slot of a slot time is that slot time ((0.05 + 0.1) * R is
    # 43200.00000000001): the same rule on both sides of a boundary keeps chunks exact.
    k0, k1 = math.ceil(t0_s * rate - SLOT_EPS), math.ceil(t1_s * rate - SLOT_EPS)
    k = np.arange(k0, max(k0, k1), dtype=np.int64)
    if spec.sector_steps < spec.steps_per_rev:
        step = (k // spec.n_channels) % spec.steps_per_rev
        k = k[step < spec.sector_steps]
    return k


def fire_times(spec: ScannerSpec, t0_s: float, t1_s: float) -> np.ndarray:
    """Firing times (s) in [t0_s, t1_s), increasing, from the integer slot grid (see module docstring)."""
    return _fire_slots(spec, t0_s, t1_s) / spec.slot_rate_hz


def max_beams_per_chunk(spec: ScannerSpec, chunk_s: float) -> int:
    """The most beams `scan_flight` fires in one chunk of chunk_s: the bound on a chunk's size."""
    return math.ceil(chunk_s * spec.slot_rate_hz) + 1


def _dirs_from_slots(spec: ScannerSpec, k: np.ndarray) -> np.ndarray:
    channel = k % spec.n_channels
    step = (k // spec.n_channels) % spec.steps_per_rev
    phi = spec.first_angle_rad + step * math.radians(spec.step_deg)
    omega = np.radians(np.asarray(spec.channel_elevations_deg, dtype=float))[channel]
    c = np.cos(omega)
    return np.stack([np.sin(omega), c * np.sin(phi), c * np.cos(phi)], axis=-1)


def beam_dirs_body(spec: ScannerSpec, t_s: np.ndarray) -> np.ndarray:
    """Unit directions (N, 3) in B of the beams fired at times t_s (times from `fire_times`).

    d_B = [sin omega, cos omega sin phi, cos omega cos phi]: phi = 0 straight down, + to starboard;
    omega = the channel's elevation, + forward (module docstring).
    """
    k = np.rint(np.asarray(t_s, dtype=float) * spec.slot_rate_hz).astype(np.int64)
    return _dirs_from_slots(spec, k)


def _rays_w(traj: Trajectory, d_body: np.ndarray, lever_arm_body_m: np.ndarray,
            frame: StorageFrame) -> tuple[np.ndarray, np.ndarray]:
    """Origins and unit directions in W (einsum, not a batched `@`: see frames._rotate)."""
    r_wb = premultiply(frame.rot_w_from_ned, rot_body_to_ned(traj.roll_rad, traj.pitch_rad, traj.yaw_rad))
    origins = frame.ned_to_w(traj.pos_ned_m) + np.einsum("nij,j->ni", r_wb, lever_arm_body_m)
    return origins, np.einsum("nij,nj->ni", r_wb, d_body)


def scan_chunk(trajectory_at: Callable[[np.ndarray], Trajectory], t0_s: float, t1_s: float,
               spec: ScannerSpec, world: World, lever_arm_body_m, frame: StorageFrame,
               rng: np.random.Generator | None = None) -> ScanChunk:
    """The returns of the beams fired in [t0_s, t1_s), each from the pose at its own firing time."""
    k = _fire_slots(spec, t0_s, t1_s)
    t = k / spec.slot_rate_hz
    origins, dirs = _rays_w(trajectory_at(t), _dirs_from_slots(spec, k), np.asarray(lever_arm_body_m, dtype=float),
                            frame)
    path = origins[k % (spec.steps_per_rev * spec.n_channels) == 0]  # each revolution's first beam
    hits = world.cast(origins, dirs, max_range_m=spec.max_range_m)  # unit dirs already: cast's norm is ~1
    ok = np.isfinite(hits.range_m)
    r = hits.range_m[ok]
    if rng is not None and spec.range_sigma_m > 0:
        r = r + rng.normal(0.0, spec.range_sigma_m, len(r))
        pts = origins[ok] + dirs[ok] * r[:, None]
    else:
        pts = hits.points_w[ok]
    return ScanChunk(float(t0_s), float(t1_s), pts, r, dirs[ok], t[ok], path, len(k))


def scan_flight(trajectory_at: Callable[[np.ndarray], Trajectory], duration_s: float, spec: ScannerSpec,
                world: World, lever_arm_body_m, frame: StorageFrame, *, chunk_s: float = 0.5,
                rng: np.random.Generator | None = None) -> Iterator[ScanChunk]:
    """Scan a flight over [0, duration_s) in chunks of chunk_s, one chunk in memory at a time.

    A chunk holds at most `max_beams_per_chunk(spec, chunk_s)` beams (144k for the 3D LiDAR at the
    default 0.5 s, ~70 MB of working arrays), so a whole-flight 3D scan (tens of millions of beams)
    streams through in bounded memory. With rng, ranges carry normal noise of spec.range_sigma_m.
    """
    if not (math.isfinite(chunk_s) and chunk_s > 0):
        raise ValueError(f"chunk length must be > 0 s, got {chunk_s}")
    n = max(1, math.ceil(duration_s / chunk_s))
    for i in range(n):
        t0, t1 = i * chunk_s, min(duration_s, (i + 1) * chunk_s)
        if t1 > t0:
            yield scan_chunk(trajectory_at, t0, t1, spec, world, lever_arm_body_m, frame, rng)
