"""Firmware in the loop, lockstep: the unchanged payload code against the simulated world.

One simulated clock (the companion computer's) drives everything. When the payload sleeps on it,
`World.advance_to` steps the vehicle (JSBSim + autopilot) and its MAVLink server up to that time;
the server's bytes reach the payload only when the payload's clock has reached the time they were
sent plus the link latency, so the payload never sees the future. The LIDAR-Lite emulator asks the
world for the true range at each acquisition, the TFMini emulator at each frame's measurement: the
vehicle's true pose at that instant (interpolated between physics steps) and the servo plant's true
shaft angle, ray traced. The TFMini's frames reach the payload's unchanged driver through an
in-memory serial port whose bytes appear at their wire times (`sitl.devices.tfmini_emu`).

The companion clock runs at an offset from the autopilot's boot clock (as on a real drone), so the
payload's time synchronisation has something to do.
"""

from __future__ import annotations

import collections
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import BinaryIO, NamedTuple, NoReturn

import numpy as np

from firmware_py.app import PayloadApp, PayloadConfig, PayloadResult
from firmware_py.core.frames import SQUARE, Boresight, StorageFrame, beam_ray_w
from firmware_py.core.geodesy import GeodeticPoint
from firmware_py.core.sensor import Rangefinder
from firmware_py.core.sensor_noise import HEADER_KEY as NOISE_HEADER_KEY
from firmware_py.core.sensor_noise import SensorNoise
from firmware_py.core.servo_model import ServoCalibration
from firmware_py.core.site import DEFAULT_SITE
from firmware_py.hal.backends import register_i2c_backend
from firmware_py.hal.clock import SimClock
from firmware_py.hal.mavlink_link import register_mavlink_backend
from firmware_py.hal.pwm import register_pwm_backend
from firmware_py.hal.uart import register_uart_backend
from firmware_py.payload import LoopStats
from sitl.mavlink.server import MavlinkVehicleServer
from sitl.sensing.noise import PoseNoiser, RangeNoiser, ServoNoiser, noise_streams
from sitl.sensing.pose_drift import HEADER_KEY as POSE_HEADER_KEY
from sitl.vehicle.api import PLANT_STATE_DTYPE, PlantState, Vehicle
from sitl.vehicle.autopilot import wrap_pi
from sitl.vehicle.jsbsim_vehicle import JsbsimVehicle
from sitl.world.raycast import World

SendAt = Callable[[int, bytes], None]
"""One direction of a link: send_at(t_ns, data) puts bytes on the wire at time t_ns."""

WALL_EPOCH_S = 1_790_000_000.0
"""The companion's wall clock (Unix s) when its simulated monotonic clock reads 0 (late 2026)."""


class DelayedPipe:
    """One direction of a link: bytes become readable `latency` after they were sent (sim time)."""

    def __init__(self, clock_ns, latency_ns=lambda: 0) -> None:
        self._clock_ns = clock_ns
        self._latency_ns = latency_ns
        self._q: collections.deque[tuple[int, bytes]] = collections.deque()
        self._last_due = 0

    def send_at(self, t_ns: int, data: bytes) -> None:
        if data:
            due = max(t_ns + int(self._latency_ns()), self._last_due)  # a serial link keeps order
            self._last_due = due
            self._q.append((due, bytes(data)))

    def recv(self) -> bytes:
        q = self._q
        if not q:
            return b""  # the payload polls every tick; most ticks nothing is due
        now = self._clock_ns()
        if q[0][0] > now:
            return b""
        out = bytearray()
        while q and q[0][0] <= now:
            out += q.popleft()[1]
        return bytes(out)


class TruePose(NamedTuple):
    """The vehicle's true pose at one instant (what the LiDAR emulator ray traces from)."""

    pos_ned_m: tuple[float, float, float]
    roll_rad: float
    pitch_rad: float
    yaw_rad: float


def plant_state_of(vehicle: Vehicle) -> PlantState:
    """The rigid-body state of any Vehicle: the plant's own report when it has one (JSBSim)."""
    s = getattr(vehicle, "plant_state", None)
    return s if s is not None else PlantState.of(vehicle.state())


def pose_from_history(hist, ts: float) -> TruePose:
    """The true pose at vehicle time ts from a time-ordered sequence of (t_s, PlantState) physics
    steps, linear between the two that bracket it (clamped at the ends)."""
    i = len(hist) - 1
    while i > 0 and hist[i - 1][0] > ts:
        i -= 1
    (t0, s0), (t1, s1) = hist[max(i - 1, 0)], hist[i]
    w = 0.0 if t1 <= t0 else min(1.0, max(0.0, (ts - t0) / (t1 - t0)))
    pos = (s0.north_m + (s1.north_m - s0.north_m) * w, s0.east_m + (s1.east_m - s0.east_m) * w,
           s0.down_m + (s1.down_m - s0.down_m) * w)
    yaw = s0.yaw_rad + wrap_pi(s1.yaw_rad - s0.yaw_rad) * w
    return TruePose(pos, s0.roll_rad + (s1.roll_rad - s0.roll_rad) * w,
                    s0.pitch_rad + (s1.pitch_rad - s0.pitch_rad) * w, wrap_pi(yaw))


def beam_range_m(world: World, frame: StorageFrame, lever_arm_body_m, pose: TruePose, servo_rad: float,
                 boresight: Boresight = SQUARE) -> float | None:
    """What the LiDAR sees from a true pose at a true servo angle (None: no return within range)."""
    o, d = beam_ray_w(pose.pos_ned_m, pose.roll_rad, pose.pitch_rad, pose.yaw_rad, servo_rad, lever_arm_body_m,
                      frame, boresight)
    r = world.cast_one(o, d)
    return None if not math.isfinite(r) else r


def beam_echo(world: World, frame: StorageFrame, lever_arm_body_m, pose: TruePose, servo_rad: float,
              boresight: Boresight = SQUARE) -> tuple[float | None, float]:
    """`beam_range_m` and the |cos| of the incidence on what the beam hit (a noise model's no-returns
    depend on it; 0 when nothing is hit)."""
    o, d = beam_ray_w(pose.pos_ned_m, pose.roll_rad, pose.pitch_rad, pose.yaw_rad, servo_rad, lever_arm_body_m,
                      frame, boresight)
    r, cos_i = world.cast_one_incidence(o, d)
    return (None, 0.0) if not math.isfinite(r) else (r, cos_i)


class TrueBeam:
    """Where the emulated LiDAR really points and what it sees: the true pose, the servo plant's true
    shaft plus the sensor-noise model's servo error (`sitl.sensing.noise.ServoNoiser`), ray traced.
    Keeps the last echo's incidence for the range noise (`RangeNoiser`), asked right after the range."""

    def __init__(self, world: World, frame: StorageFrame, lever_arm_body_m, pose_at: Callable[[int], TruePose],
                 servo_angle_at: Callable[[int], float] | None) -> None:
        self.world, self.frame, self.pose_at, self.servo_angle_at = world, frame, pose_at, servo_angle_at
        self.lever = tuple(float(v) for v in lever_arm_body_m)  # plain floats: read at every sample
        self.boresight = SQUARE  # the beam's true mounting (a fault may tilt it)
        self.servo_noise = None  # a ServoNoiser, or None: the shaft exactly
        self.incidence_needed = False  # a range noise model asks for the incidence
        self.last_cos_incidence = 1.0

    def range_m(self, t_ns: int) -> float | None:
        gamma = self.servo_angle_at(t_ns) if self.servo_angle_at else 0.0
        if self.servo_noise is not None:
            gamma += self.servo_noise.error()
        pose = self.pose_at(t_ns)
        if not self.incidence_needed:
            return beam_range_m(self.world, self.frame, self.lever, pose, gamma, self.boresight)
        r, self.last_cos_incidence = beam_echo(self.world, self.frame, self.lever, pose, gamma, self.boresight)
        return r


class SimWorld:
    """Vehicle + MAVLink server + building, advanced in lockstep with the payload's clock."""

    def __init__(self, vehicle: Vehicle, world: World, frame: StorageFrame, clock: SimClock,
                 boot_offset_ns: int, lever_arm_body_m, latency_ns=lambda: 0, tlog_path=None, signing=None,
                 home: GeodeticPoint = DEFAULT_SITE.corner) -> None:
        self.vehicle, self.world, self.frame, self.clock = vehicle, world, frame, clock
        self.boot_offset_ns = boot_offset_ns  # companion time = vehicle time + offset
        self.lever = tuple(float(v) for v in lever_arm_body_m)  # plain floats: read at every sample
        self._down = DelayedPipe(clock.now_ns, latency_ns)
        self.server = MavlinkVehicleServer(vehicle, _ServerSide(self), tlog_path=tlog_path, signing=signing,
                                           home=home)
        self._up = DelayedPipe(self._vehicle_now_companion_ns, latency_ns)
        self._down_send_at, self._up_send_at = self._down.send_at, self._up.send_at
        self._hist: collections.deque[tuple[float, PlantState]] = collections.deque(maxlen=64)
        # The vehicle's clock and rigid-body state are read after every physics step: straight from
        # the JSBSim plant when there is one (no VehicleState built just for its t_s).
        self._vehicle_time_s: Callable[[], float] = getattr(vehicle, "time_s", None) or (lambda: vehicle.state().t_s)
        if isinstance(vehicle, JsbsimVehicle):
            self._plant_state: Callable[[], PlantState] = lambda: vehicle.plant_state
        else:
            self._plant_state = lambda: plant_state_of(vehicle)
        self._vehicle_t_s = self._vehicle_time_s()  # the vehicle steps only here: its clock, kept
        self._hist.append((self._vehicle_t_s, plant_state_of(vehicle)))
        self.history: list[tuple[float, PlantState]] = [self._hist[-1]]  # the whole true flight
        self.pose_errors: list[tuple[float, float, float, float]] | None = None
        """The vehicle's estimator error beside each `history` entry, once `record_pose_errors` is called."""
        self.beam = TrueBeam(world, frame, self.lever, self.pose_at, None)  # the runner sets its servo
        clock.set_advance(self.advance_to)

    def record_pose_errors(self) -> None:
        """Keep the vehicle's `pose_error` (its estimate minus the truth) beside every true state from now
        on; the history so far gets the current one."""
        err = tuple(getattr(self.vehicle, "pose_error", (0.0, 0.0, 0.0, 0.0)))
        self.pose_errors = [err] * len(self.history)

    @property
    def servo_angle_at(self) -> Callable[[int], float] | None:
        """t_ns -> the servo plant's true shaft angle (set by the runner)."""
        return self.beam.servo_angle_at

    @servo_angle_at.setter
    def servo_angle_at(self, f: Callable[[int], float] | None) -> None:
        self.beam.servo_angle_at = f

    @property
    def boresight(self) -> Boresight:
        """The beam's true mounting (a fault may tilt it)."""
        return self.beam.boresight

    @boresight.setter
    def boresight(self, b: Boresight) -> None:
        self.beam.boresight = b

    # -- the payload's end of the MAVLink link ---------------------------------------------------
    def wrap_links(self, wrap: Callable[[str, SendAt], SendAt]) -> None:
        """Put something between each end of the MAVLink link and its pipe (fault injection, tests):
        `wrap(direction, send_at)` returns the send_at to use instead; direction is "down" (autopilot
        to payload) or "up". Wrappers stack: a later one wraps the earlier."""
        self._down_send_at = wrap("down", self._down_send_at)
        self._up_send_at = wrap("up", self._up_send_at)

    def payload_send(self, data: bytes) -> None:
        self._up_send_at(self.clock.now_ns(), data)

    def payload_recv(self) -> bytes:
        return self._down.recv()

    def _vehicle_now_companion_ns(self) -> int:
        return round(self._vehicle_t_s * 1e9) + self.boot_offset_ns

    # -- time ------------------------------------------------------------------------------------
    def vehicle_time_ns(self, companion_ns: int) -> int:
        return companion_ns - self.boot_offset_ns

    def advance_to(self, t_ns: int) -> int:
        """Step the vehicle until its clock has passed companion time t_ns; return the companion
        time up to which it is now stepped (the clock's horizon: no call needed before it)."""
        target_s = self.vehicle_time_ns(t_ns) * 1e-9
        vehicle, hist, history = self.vehicle, self._hist, self.history
        if hist[-1][0] >= target_s:
            return math.floor(hist[-1][0] * 1e9) + self.boot_offset_ns
        step, update, time_s, plant_state = vehicle.step, self.server.update, self._vehicle_time_s, self._plant_state
        errors = self.pose_errors
        while hist[-1][0] < target_s:
            step()
            t_s = self._vehicle_t_s = time_s()
            update()
            entry = (t_s, plant_state())
            hist.append(entry)
            history.append(entry)
            if errors is not None:
                errors.append(vehicle.pose_error)
        return math.floor(hist[-1][0] * 1e9) + self.boot_offset_ns

    def pose_at(self, t_ns: int) -> TruePose:
        """The vehicle's true pose at companion time t_ns (linear between physics steps)."""
        if t_ns > self.clock.now_ns():  # the clock has stepped the world up to its own time already
            self.advance_to(t_ns)
        return pose_from_history(self._hist, self.vehicle_time_ns(t_ns) * 1e-9)

    def true_range_m(self, t_ns: int) -> float | None:
        """What the LiDAR sees at companion time t_ns: true pose, true servo angle, ray traced."""
        return self.beam.range_m(t_ns)


class _ServerSide:
    """The server's transport: what it sends goes down the delayed pipe; it reads what is due."""

    def __init__(self, world: SimWorld) -> None:
        self._world = world

    def send(self, data: bytes) -> None:
        self._world._down_send_at(self._world._vehicle_now_companion_ns(), data)

    def recv(self) -> bytes:
        return self._world._up.recv()

    def close(self) -> None:
        pass


class _PowerCut(BaseException):
    """Raised from the app's tick hook: the payload loses power mid-flight. A BaseException, so no
    handler in the program mistakes it for an error it can recover from."""


class _Power:
    """The payload computer's supply: once cut, nothing it does reaches the world any more (its log
    file takes no more bytes, its link sends nothing), whatever its shutdown code still tries."""

    def __init__(self) -> None:
        self.on = True

    def opener(self, inner: Callable[[str, str], BinaryIO]) -> Callable[[str, str], BinaryIO]:
        return lambda path, mode: _PoweredFile(inner(path, mode), self)


class _PoweredFile:
    """A file whose writes stop reaching the disk when the power goes (what was written stays)."""

    def __init__(self, f: BinaryIO, power: _Power) -> None:
        self._f, self._power = f, power

    def write(self, data) -> int:
        return self._f.write(data) if self._power.on else len(data)

    def flush(self) -> None:
        if self._power.on:
            self._f.flush()

    def __getattr__(self, name: str):
        return getattr(self._f, name)


@dataclass(frozen=True)
class FirmwareRun:
    """What a firmware-in-the-loop flight produced."""

    records: np.ndarray
    duration_s: float
    energy_j: float
    completed: bool
    loop: LoopStats
    lidar_counters: dict
    pose_status: dict
    true_t_s: np.ndarray  # the vehicle's true flight, companion seconds
    true_states: np.ndarray  # (N,) of PLANT_STATE_DTYPE, at true_t_s
    faults: dict | None = None  # what the fault injector did (counters), when faults were injected
    result: PayloadResult | None = None  # how the payload program ended (None: it lost power)
    true_pose_error: np.ndarray | None = None  # (N, 4) the estimator's error at true_t_s (None: flown on the truth)
    world: World | None = None  # the building and pile the flight was ray-cast in (the runner's clearance checks)


NOISE_SEED_TAG = 0x5E45
"""Mixed into the run's seed for the sensor-noise draws: independent of its latency and fault draws."""
SITL_MAVLINK_URL = "sitl:lockstep"
SITL_I2C_URL = "sitl:lockstep"
SITL_PWM_URL = "pwm:sitl"
SITL_UART_URL = "sitl:lockstep"
"""What the lockstep run's header names as the payload's hardware: the parts are injected, not opened."""
POSE_WAIT_S = 30.0
SURVEY_FLOWN = "survey flown"
STOP_MESSAGE_WAIT_S = 0.5
"""Simulated time after the payload stops for its last messages to cross the link (latency, faults)."""


def _not_opened(url: str, **_options: object) -> NoReturn:
    raise ValueError(f"{url}: the lockstep SITL injects its parts; nothing to open")


def _register_injected_schemes() -> None:
    """The `sitl` scheme of each part the lockstep flight injects, refusing to open: the payload's configuration
    checks every URL against the schemes its process knows, and these name injected parts. Registered again
    before each flight's configuration, as a test may have unregistered a scheme of that name (its own bus)."""
    register_mavlink_backend("sitl", _not_opened)
    register_i2c_backend("sitl", _not_opened)
    register_uart_backend("sitl", _not_opened)
    register_pwm_backend("sitl", _not_opened)


def payload_config(cfg, log_path, header: dict, timeout_s: float) -> PayloadConfig:
    """The payload program's configuration for a lockstep flight of `cfg` (a FlyConfig), with the
    SITL's header provenance (source, mission) so the ground station reads the same log header. The
    payload sends the flight's EKF origin (SET_GPS_GLOBAL_ORIGIN), as `pilescan-payload --origin` does:
    the simulated autopilot's home, where its plant and its plan are placed too."""
    _register_injected_schemes()
    return PayloadConfig(
        out_path=log_path, force=True, mavlink_url=SITL_MAVLINK_URL, i2c_url=SITL_I2C_URL, pwm_url=SITL_PWM_URL,
        rangefinder=cfg.rangefinder, uart_url=SITL_UART_URL, rate_hz=cfg.lidar.rate_hz, waveform=cfg.waveform,
        servo_peak_rate_rad_s=cfg.servo_peak_rate_rad_s,
        initial_position=cfg.initial_position, servo=ServoCalibration(), storage=cfg.mission.storage,
        frame=cfg.frame, site=cfg.site, lever_arm_body_m=tuple(cfg.lever_arm_body_m),
        range_sigma_m=cfg.lidar.range_sigma_m,
        range_sigma_rel=cfg.lidar.range_sigma_rel, duration_s=timeout_s, stop_on_disarm=True,
        send_origin=cfg.ekf_origin.as_tuple(), mission_id=header.get("mission_id"), fsync=False, quiet=True,
        wait_for_pose_s=POSE_WAIT_S, source=header.get("source", "sitl"), mission=header.get("mission"),
        header_extra={k: header[k] for k in (NOISE_HEADER_KEY, POSE_HEADER_KEY) if k in header} or None)


def attach_sensor_noise(noise: SensorNoise, seed: int, server: MavlinkVehicleServer,
                        beam: TrueBeam | None) -> RangeNoiser | None:
    """Put a sensor-noise model into a simulated flight (lockstep or networked): the servo error on the
    true beam, the pose error on what the autopilot reports; returns the range noise for the emulated
    rangefinder (None: none). Draws come from `noise_streams(seed)`, so a run repeats with its seed."""
    if not noise.active:
        return None
    rngs = noise_streams([seed, NOISE_SEED_TAG])
    if noise.pose_noisy:
        server.pose_noise = PoseNoiser(noise, rngs)
    if beam is None:
        return None  # no emulated devices: the autopilot's pose error only
    if noise.servo_sigma_rad > 0:
        beam.servo_noise = ServoNoiser(noise, rngs)
    beam.incidence_needed = noise.returns is not None
    return RangeNoiser(noise, rngs, incidence=lambda: beam.last_cos_incidence)


def fly_firmware(cfg, log_path, header: dict, latency_ms: tuple[float, float] = (0.0, 0.0),
                 boot_offset_s: float = 1234.5, tlog_path=None, seed: int = 0, faults=None,
                 signing_key: bytes | None = None) -> FirmwareRun:
    """Fly `cfg` (a sitl.runners.fly.FlyConfig) with the payload program (`PayloadApp`) in the loop.

    The vehicle settles on W0 with the payload off; the payload program starts on the simulated clock,
    MAVLink link, I2C bus and servo output, waits for a trusted pose, and the survey starts at its first
    sample. Back on W0 the operator stops the program (`request_stop`, what its SIGTERM handler calls);
    it also stops on a disarm (`stop_on_disarm`). Its health NAMED_VALUE_FLOATs and STATUSTEXTs reach
    the autopilot and its .tlog. `header` gives the log's provenance (source, mission); the program
    writes the rest.
    `faults` (a sitl.faults.injector.FaultSpec) injects link, sensor, servo, autopilot, clock and power
    faults; a power cut ends the run there, leaving the log as the cut leaves it. With
    `signing_key` both ends sign (MAVLink 2) and refuse what is not, each stamping with its own
    simulated wall clock (the companion's can jump: the clock_jump fault).
    """
    from firmware_py.core.samplelog import read_samplelog
    from firmware_py.hal.mavlink_link import ByteStreamLink
    from sitl.devices.i2c_sim import SimI2CBus
    from sitl.devices.lidarlite_emu import EmulatedLidarLite
    from sitl.devices.servo_emu import EmulatedServo
    from sitl.devices.tfmini_emu import EmulatedTfminiPort
    from sitl.faults.injector import FaultInjector
    from sitl.runners.flight import SETTLE_S, mission_nav_items, start_pose
    from sitl.sensing.pose_drift import make_drift, world_ground_below
    from sitl.vehicle.api import FlightMode
    from sitl.vehicle.jsbsim_plant import PlantConfig
    from sitl.vehicle.jsbsim_vehicle import VehicleConfig
    from sitl.world import stockpile as piles

    m = cfg.mission
    start, yaw0 = start_pose(m, cfg.frame)
    vcfg = VehicleConfig(plant=PlantConfig(payload_kg=cfg.payload_kg, start_ned_m=start, start_yaw_rad=yaw0,
                                           airborne=True, origin=cfg.ekf_origin),
                         speed_m_s=m.speed_m_s, yaw_rate_max_rad_s=m.yaw_rate_max_rad_s, altitude_m=m.altitude_m)
    vehicle = JsbsimVehicle(vcfg, armed=True, mode=FlightMode.GUIDED)
    pile = piles.resolve(cfg.stockpile, m.storage)
    world = World(m.storage, pile, max_range_m=cfg.lidar.max_range_m)
    drift = make_drift(cfg.pose_error, seed, world_ground_below(world, cfg.frame))
    if drift is not None:
        vehicle.attach_drift(drift)  # the autopilot flies on, and reports, its estimate
    rng = np.random.default_rng(seed)
    lo, hi = latency_ms
    latency = (lambda: 0) if hi <= 0 else (lambda: int(rng.uniform(lo, hi) * 1e6))
    clock = SimClock(start_ns=round(boot_offset_s * 1e9))
    inj = FaultInjector(faults) if faults is not None and faults.active else None  # none: the plain path
    true_wall_s = lambda: WALL_EPOCH_S + clock.now_ns() * 1e-9  # noqa: E731
    companion_wall_s = inj.wall_clock(true_wall_s) if inj is not None else true_wall_s
    server_signer = payload_signer = None
    if signing_key is not None:
        from firmware_py.hal.signing import MavlinkSigner, SigningConfig
        server_signer = MavlinkSigner(SigningConfig(signing_key), clock=true_wall_s)
        payload_signer = MavlinkSigner(SigningConfig(signing_key), clock=companion_wall_s)
    sim = SimWorld(vehicle, world, cfg.frame, clock, boot_offset_ns=round(boot_offset_s * 1e9),
                   lever_arm_body_m=cfg.lever_arm_body_m, latency_ns=latency, tlog_path=tlog_path,
                   signing=server_signer, home=cfg.ekf_origin)
    if drift is not None:
        sim.record_pose_errors()
    links = {}
    if inj is not None:
        def wrap(direction: str, send_at: SendAt) -> SendAt:
            links[direction] = inj.link(send_at)
            return links[direction].send_at
        sim.wrap_links(wrap)
        inj.reboot = sim.server.reboot
    # The vehicle settles on W0 with the payload still off: what the autopilot sends meanwhile is lost.
    clock.sleep_until_ns(clock.now_ns() + round(SETTLE_S * 1e9))
    sim.payload_recv()
    wf = cfg.servo_waveform()
    cal = ServoCalibration()
    plant = EmulatedServo(clock, cal, angle0_rad=float(wf.angle(0.0)))
    sim.servo_angle_at = plant.angle_at
    range_at = inj.range_at(sim.true_range_m) if inj else sim.true_range_m
    noisers = attach_sensor_noise(cfg.noise(), seed, sim.server, sim.beam)
    bus = uart = None
    if cfg.rangefinder is Rangefinder.TFMINI:
        uart = EmulatedTfminiPort(clock, range_at, rate_hz=cfg.lidar.rate_hz, range_noise=noisers,
                                  rng=np.random.default_rng([seed, 0x7F]))
        part = None
    else:
        bus = SimI2CBus(clock)
        part = EmulatedLidarLite(clock, range_at, range_noise=noisers)
        bus.attach(0x62, part)
    if inj is not None:
        inj.attach(bus, part, plant)
        if uart is not None:
            inj.attach_tfmini(uart)
        sim.boresight = inj.boresight
    power = _Power()
    link = ByteStreamLink(lambda data: sim.payload_send(data) if power.on else None, sim.payload_recv,
                          signing=payload_signer)
    disk = inj.opener(clock.now_ns) if inj is not None and faults.disk_full_at_s is not None else open
    timeout_s = 3 * (m.path_length_m() / m.speed_m_s + 2 * math.pi / m.yaw_rate_max_rad_s) + 60
    pcfg = payload_config(cfg, log_path, header, timeout_s)
    survey: dict = {"t0_s": None, "e0_j": 0.0, "flown": False}

    def on_tick(now: int) -> None:
        """The SITL's side of every payload tick: the survey's start and end, the fault schedule."""
        if survey["t0_s"] is None:  # the payload samples: fly the survey
            vehicle.load_mission(mission_nav_items(m, cfg.frame))
            vehicle.start_mission()
            survey["t0_s"], survey["e0_j"] = vehicle.state().t_s, vehicle.plant.energy_j
            if inj is not None:
                inj.start_survey(now)
        elif not survey["flown"] and vehicle.mode != FlightMode.AUTO:
            survey["flown"] = True  # back on W0: the operator stops the payload (its SIGTERM)
            app.request_stop(SURVEY_FLOWN)
        if inj is not None:
            inj.tick(now)
            if inj.power_cut_due(now):
                power.on = False
                raise _PowerCut

    app = PayloadApp(pcfg, clock=clock, link=link, bus=bus, pwm=plant, uart=uart, err=None,
                     open_log=power.opener(disk), on_tick=on_tick)
    cut = False
    disk_full: bool | str = False
    result = None
    try:
        result = app.run()
    except _PowerCut:
        cut = True
    except OSError as exc:  # the disk filled: pilescan-payload stops with this error (exit 1)
        if inj is None or faults.disk_full_at_s is None:
            raise
        disk_full = str(exc)
    ts0 = survey["t0_s"] if survey["t0_s"] is not None else vehicle.state().t_s
    duration_s, energy_j = vehicle.state().t_s - ts0, vehicle.plant.energy_j - survey["e0_j"]
    # What the payload sent last (its stop message) reaches the autopilot and its .tlog.
    clock.sleep_until_ns(clock.now_ns() + round(STOP_MESSAGE_WAIT_S * 1e9))
    sim.server.close()
    loop, lidar = app.loop, app.lidar
    status = app.tracker.status().as_dict() if app.tracker is not None else {}
    true_t = np.array([t for t, _ in sim.history]) + boot_offset_s
    true_s = np.array([st for _, st in sim.history], dtype=PLANT_STATE_DTYPE)
    completed = (not (cut or disk_full) and survey["flown"] and vehicle.current_item() == -1
                 and result is not None and result.stop_reason == SURVEY_FLOWN)
    return FirmwareRun(read_samplelog(log_path).samples, duration_s, energy_j, completed, loop.stats,
                       lidar.counters().as_dict(), status, true_t, true_s,
                       None if inj is None else
                       {"link_down": links["down"].counters, "link_up": links["up"].counters, **inj.counters,
                        "i2c_nacks": bus.counters["nack"] if bus is not None else 0,
                        **({"tfmini_bad_frames_sent": uart.source.bad_frames_sent,
                            "tfmini_garbage_bursts": uart.source.garbage_bursts} if uart is not None else {}),
                        "power_cut": cut, "disk_full": disk_full,
                        "loop": loop.stats, "pending_at_stop": loop.pending if (cut or disk_full) else 0,
                        "signing": {"payload": dict(payload_signer.stats), "autopilot": dict(server_signer.stats)}
                        if signing_key is not None else None,
                        "autopilot_reboots": sim.server.stats.get("reboots", 0)},
                       result, None if sim.pose_errors is None else np.array(sim.pose_errors, dtype=float),
                       world)
