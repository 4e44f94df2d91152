"""`pilescan-sitl serve`: the simulated vehicle as a networked MAVLink autopilot, paced to the wall clock.

The vehicle waits on the floor below W0 of the survey (the plan's home), disarmed. The plan is
written next to the telemetry log so a ground station can load it; the local NED origin (the
storage frame's corner) is the EKF origin both use for global positions.

With `signing` (`--signing-key FILE`) the autopilot signs everything it sends and refuses unsigned,
forged and replayed frames; a UDP client is only sent to once it has sent a signed frame
(MAVProxy: `signing setup PASSPHRASE`, or `signing key FILE` with the same key, before connecting;
pymavlink: `conn.setup_signing(key)`). The same key authenticates the emulated device bridge
(--devices): a payload must prove it holds the key before it may touch the LiDAR or the servo.

Faults (`--fault NAME=VALUE`, `--seed`; `sitl.devices.networked.NetworkedFaults`): the FaultSpec faults of
`pilescan-sitl fly` that make sense here, on the MAVLink link, the autopilot and the emulated devices,
timed from the start of the mission (the vehicle first entering AUTO). The `SIM_PS_*` parameters
(`sitl.faults.params`) change the injection while it runs, from any ground station.

With `--devices` it prints the payload's command line (`payload_command`): every option the payload needs to fly
this survey against it (the MAVLink and device URLs, the TFMini's pseudo-terminal, the building, the site, the key,
the sample log in the run directory), runnable as printed.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import shlex
import signal
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from firmware_py.core.cli import reading_input
from firmware_py.core.frames import StorageFrame
from firmware_py.core.geodesy import GeodeticPoint
from firmware_py.core.rundir import (
    PILE_FILE,
    PLAN_FILE,
    RUN_FILES,
    SAMPLES_FILE,
    TLOG_FILE,
    TRUTH_FILE,
    OutputFolder,
    check_free,
)
from firmware_py.core.sensor import Rangefinder
from firmware_py.core.sensor_noise import SensorNoiseModel, noise_summary
from firmware_py.core.site import DEFAULT_SITE, Site
from firmware_py.hal.signing import SigningConfig
from sitl.devices.bridge_server import parse_bridge_url
from sitl.devices.networked import SERVO_CHANNEL, NetworkedDevices, NetworkedFaults, check_networked_faults
from sitl.faults.injector import PAIRS, FaultSpec
from sitl.mavlink.server import LinkLimits, MavlinkVehicleServer, run_realtime
from sitl.mavlink.transport import make_transport, parse_udp_url
from sitl.missions.qgc_wpl import write_qgc_wpl
from sitl.missions.range_check import RangeLimit, check_range
from sitl.missions.rectangle import Mission
from sitl.runners.flight import start_pose
from sitl.runners.fly import (
    TRAJECTORY_RATE_HZ,
    FlyConfig,
    check_clearance,
    check_rangefinder_faults,
    drift_warning,
    noise_header,
    pose_error_header,
    pose_error_truth,
    truth_record,
)
from sitl.runners.lockstep_payload import attach_sensor_noise
from sitl.sensing.pose_drift import HEADER_KEY as POSE_ERROR_KEY
from sitl.sensing.pose_drift import PoseErrorProfile, make_drift, world_ground_below
from sitl.vehicle.jsbsim_plant import PlantConfig
from sitl.vehicle.jsbsim_vehicle import JsbsimVehicle, VehicleConfig
from sitl.vehicle.kinematic_vehicle import KinematicVehicle
from sitl.world import stockpile as piles
from sitl.world.clearance import closest_approach, collision, f450_pile_approach, f450_reach_m, pile_collision
from sitl.world.raycast import World

VEHICLES = ("jsbsim", "kinematic")
TAKEOFF_CLEAR_M = 0.05
"""Material thinner than this under the waiting vehicle is the floor's own roughness, not a pile it sits in."""
log = logging.getLogger(__name__)


def make_vehicle(kind: str, mission: Mission, frame: StorageFrame, origin: GeodeticPoint = DEFAULT_SITE.corner,
                 takeoff_w: tuple[float, float] | None = None):
    """The served vehicle, on the floor below W0 (or at takeoff_w, W) facing along the closing leg; origin: where on
    Earth its local NED frame's origin is (the JSBSim plant flies over the ellipsoid there)."""
    (n, e, _), yaw = start_pose(mission, frame)
    if takeoff_w is not None:
        n, e, _ = (float(v) for v in frame.w_to_ned([takeoff_w[0], takeoff_w[1], 0.0]))
    if kind == "kinematic":
        return KinematicVehicle(speed_m_s=mission.speed_m_s, yaw_rate_max_rad_s=mission.yaw_rate_max_rad_s,
                                altitude_m=mission.altitude_m, home_ned_m=(n, e, 0.0))
    return JsbsimVehicle(VehicleConfig(plant=PlantConfig(start_ned_m=(n, e, 0.0), start_yaw_rad=yaw, origin=origin),
                                       speed_m_s=mission.speed_m_s,
                                       yaw_rate_max_rad_s=mission.yaw_rate_max_rad_s, altitude_m=mission.altitude_m))


SIMULATOR_CLOCK = "simulator"
"""truth.json's trajectory ``clock`` from `serve`: the simulator's seconds, not the payload log's (a networked
payload stamps its samples with its own monotonic clock; `tools.fly_networked` aligns the two)."""


@dataclass(frozen=True)
class ServeOptions:
    """What `pilescan-sitl serve` runs; checked at construction, before anything is opened or written."""

    mission: Mission
    url: str = "udp:127.0.0.1:14550"
    speedup: float = 1.0
    duration_s: float | None = None
    vehicle: str = "jsbsim"
    out: Path = Path("runs/serve")
    force: bool = False  # replace a run already in `out` (its truth.json first)
    devices_url: str | None = None
    stockpile: str = "1"
    signing: SigningConfig | None = None
    signing_key_file: str | None = None
    """The --signing-key file `signing` was read from: the payload's command line names it."""
    faults: FaultSpec = field(default_factory=FaultSpec)
    """The --fault faults (timed ones count from the mission start); its seed seeds every fault draw,
    the SIM_PS_* parameters' too."""
    limits: LinkLimits = field(default_factory=LinkLimits)
    """What one MAVLink sender may cost the others (STATUSTEXT answers, tlog space; --tlog-max-mb)."""
    rangefinder: Rangefinder = Rangefinder.LIDARLITE_V3
    """With --devices: the TFMini also streams on a pseudo-terminal (the LIDAR-Lite is always on the bridge)."""
    site: Site = DEFAULT_SITE
    """Where the building stands (--origin, --heading): the EKF origin and home are its floor corner."""
    sensor_noise: SensorNoiseModel = SensorNoiseModel.NONE
    """--sensor-noise: the servo error on the emulated LiDAR's beam, the range noise of its datasheet or of
    Appendix A, the pose error on ATTITUDE and LOCAL_POSITION_NED (seeded by the faults' seed, --seed)."""
    pose_error: PoseErrorProfile = PoseErrorProfile.NONE
    """--pose-error: the indoor estimate the JSBSim vehicle flies on and reports (seeded by --seed)."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.speedup) and 0 < self.speedup <= 1000):
            raise ValueError(f"--speedup must be in (0, 1000], got {self.speedup:g}")
        if self.duration_s is not None and not self.duration_s > 0:
            raise ValueError(f"--duration must be > 0 s, got {self.duration_s:g}")
        if self.devices_url is not None and self.speedup != 1.0:
            raise ValueError("--devices needs --speedup 1: the payload on the other end runs on the wall clock")
        if self.vehicle not in VEHICLES:
            raise ValueError(f"unknown vehicle {self.vehicle!r}; available: {', '.join(VEHICLES)}")
        seed = self.faults.seed
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise ValueError(f"seed must be an integer >= 0, got {seed!r}")
        check_networked_faults(self.faults, devices=self.devices_url is not None)
        if not isinstance(self.rangefinder, Rangefinder):
            raise ValueError(f"rangefinder must be one of {', '.join(r.value for r in Rangefinder)}, "
                             f"got {self.rangefinder!r}")
        if self.rangefinder is Rangefinder.TFMINI and self.devices_url is None:
            raise ValueError("--rangefinder tfmini needs --devices (the emulated parts the payload uses)")
        check_rangefinder_faults(self.rangefinder, self.faults)
        object.__setattr__(self, "sensor_noise", SensorNoiseModel(self.sensor_noise))
        object.__setattr__(self, "pose_error", PoseErrorProfile(self.pose_error))
        if self.pose_error is not PoseErrorProfile.NONE and self.vehicle != "jsbsim":
            raise ValueError(f"--pose-error {self.pose_error.value} needs --vehicle jsbsim (the kinematic vehicle has "
                             "no autopilot to fly on an estimate)")
        if not isinstance(self.site, Site):
            raise ValueError(f"site must be a Site, got {self.site!r}")

    def fly_config(self) -> FlyConfig:
        """The lockstep SITL's settings for this mission: its frame, lever arm and LiDAR are served too."""
        return FlyConfig(mission=self.mission, stockpile=self.stockpile, rangefinder=self.rangefinder, site=self.site,
                         sensor_noise=self.sensor_noise, pose_error=self.pose_error, seed=self.faults.seed)


def serve(opts: ServeOptions) -> int:
    """Serve until opts.duration_s of simulated time has run, or SIGINT / SIGTERM; returns the exit code.

    What it does goes to the operator through `logging` (listening, clients, arming, modes, missions,
    landing): INFO lines of the `sitl` loggers on stderr, prefixed "pilescan-sitl:" (`_operator_log`).
    """
    world = None
    check_free(opts.out, RUN_FILES, force=opts.force)  # a taken --out fails before any work
    drift = drift_warning(opts.mission, opts.pose_error)  # the served vehicle flies on the drifting estimate
    if drift:
        log.warning(drift)
    spot = None  # where the vehicle waits: below the first waypoint unless material stands there (takeoff_spot)
    if opts.devices_url is not None:
        parse_bridge_url(opts.devices_url)  # a bad URL fails before any work
        with reading_input("--stockpile"):
            pile = piles.resolve(opts.stockpile, opts.mission.storage)
        check_clearance(opts.mission, pile, opts.pose_error)
        fc = opts.fly_config()
        out_of_range = check_range(opts.mission, RangeLimit(fc.lidar.max_range_m, fc.noise().returns, fc.lidar.model),
                                   fc.servo_waveform(), fc.lever_arm_body_m)
        if out_of_range:
            log.warning(out_of_range)
        world = World(opts.mission.storage, pile, max_range_m=opts.fly_config().lidar.max_range_m)
        spot = takeoff_spot(opts.mission, world)
        if spot is not None:
            log.info(spot.describe(tuple(float(v) for v in opts.mission.waypoints_w()[0])))
        elif buried := takeoff_under_pile(opts.mission, world):
            log.warning(buried)
    transport = make_transport(opts.url)  # a bad --mavlink fails before anything is written
    try:
        # The folder is locked while served; the plan is put in place at once (a ground station loads
        # it), the telemetry log and the truth when the vehicle stops, the truth last (rundir).
        with _operator_log(), OutputFolder(opts.out, RUN_FILES, TRUTH_FILE, force=opts.force) as folder:
            code = _serve(opts, world, transport, folder, spot)
            folder.commit()
            return code
    finally:
        transport.close()


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever sys.stderr is when a line is logged (a test's capture, a redirected stream)."""

    def emit(self, record: logging.LogRecord) -> None:
        self.setStream(sys.stderr)
        super().emit(record)


@contextlib.contextmanager
def _operator_log() -> Iterator[None]:
    """The `sitl` loggers' INFO lines on stderr, prefixed "pilescan-sitl:", unless a handler is already
    set on them (a program that configures logging itself); removed again afterwards."""
    logger = logging.getLogger("sitl")
    if logger.handlers:
        yield
        return
    handler = _StderrHandler()
    handler.setFormatter(logging.Formatter("pilescan-sitl: %(message)s"))
    level, propagate = logger.level, logger.propagate
    logger.addHandler(handler)
    if level == logging.NOTSET:
        logger.setLevel(logging.INFO)
    logger.propagate = False
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
        logger.propagate = propagate


def _where(transport) -> str:
    at = _address(transport)
    return "?" if at is None else f"{at[0]}:{at[1]}"


def _address(transport) -> tuple[str, int] | None:
    """Where the transport is bound (host, port), or None when it cannot say."""
    try:
        host, port = transport.local_address
        return str(host), int(port)
    except (AttributeError, OSError, TypeError, ValueError):
        return None


def _client_host(host: str) -> str:
    """Where a client on this machine reaches a host serve listens on: a wildcard is the loopback; an IPv6
    address in brackets."""
    host = host.strip("[]")
    host = {"": "127.0.0.1", "0.0.0.0": "127.0.0.1", "::": "::1"}.get(host, host)
    return f"[{host}]" if ":" in host else host


def _num(v: float) -> str:
    """A number as short as it reads back exactly ('30', '12.5')."""
    short = f"{v:g}"
    return short if float(short) == v else repr(float(v))


def payload_command(opts: ServeOptions, *, mavlink_at: tuple[str, int] | None, devices_url: str,
                    tfmini_path: str | None = None, run_dir: Path | None = None) -> list[str]:
    """The `pilescan-payload` command line (argv) that surveys with this serve: its MAVLink link (a client of
    serve's listening UDP port, actually bound at `mavlink_at`; or the fixed peer serve sends to), the devices
    (`--hal sitl:` for the LIDAR-Lite; the TFMini's `--uart serial:PTY` and the servo's `--pwm` on the bridge),
    the building (`--storage`), the site when not the default (`--origin`, `--heading`), the key file
    (`--signing-key`), the sample log in the run directory (`--out`) and `--stop-on-disarm` (one log per flight).
    The payload has no --altitude: the flight height is the plan's, which the ground station uploads."""
    kind, host, port = parse_udp_url(opts.url)
    if kind == "udpin":  # serve listens (udp:, udpin:): the payload is a client of where it listens
        if mavlink_at is not None:
            host, port = mavlink_at
        mavlink = f"udpout:{_client_host(host)}:{port}"
    else:  # udpout: serve sends to a fixed address, where the payload listens
        mavlink = f"udp:{host}:{port}"
    dev_host, dev_port = parse_bridge_url(devices_url)
    dev_host = _client_host(dev_host)
    bridge = f"tcp:{dev_host}:{dev_port}"
    argv = ["pilescan-payload", "--mavlink", mavlink]
    if tfmini_path is not None:
        argv += ["--rangefinder", "tfmini", "--uart", f"serial:{tfmini_path}", "--pwm",
                 f"pwm:{bridge}:{SERVO_CHANNEL}"]
    elif dev_host.startswith("["):  # --hal takes no IPv6 address: both URLs in full
        argv += ["--i2c", bridge, "--pwm", f"pwm:{bridge}:{SERVO_CHANNEL}"]
    else:
        argv += ["--hal", f"sitl:{dev_host}:{dev_port}"]
    st = opts.mission.storage
    argv += ["--storage", f"{_num(st.length_m)}x{_num(st.width_m)}x{_num(st.height_m)}"]
    if opts.site != DEFAULT_SITE:  # the payload's header and the origin it sends agree with the served autopilot's
        c = opts.site.corner
        argv += [f"--origin={_num(c.lat_deg)},{_num(c.lon_deg)},{_num(c.alt_m)}",
                 f"--heading={_num(opts.site.heading_deg)}"]
    if opts.signing is not None:
        argv += ["--signing-key", str(opts.signing_key_file) if opts.signing_key_file is not None else "KEY_FILE"]
    argv += ["--out", str((run_dir if run_dir is not None else opts.out) / SAMPLES_FILE), "--stop-on-disarm"]
    return argv


TAKEOFF_GRID_M = 0.25
"""The spacing of the floor points searched for a clear take-off spot."""


@dataclass(frozen=True)
class TakeoffSpot:
    """Where the served vehicle waits and takes off (W, m), and how much material stands below the first waypoint."""

    xy_w: tuple[float, float]
    material_at_w0_m: float

    def describe(self, w0: tuple[float, float]) -> str:
        return (f"the vehicle waits on clear floor at ({self.xy_w[0]:.1f}, {self.xy_w[1]:.1f}) m, the nearest to the "
                f"first waypoint ({w0[0]:.1f}, {w0[1]:.1f}) m, where the pile stands {self.material_at_w0_m:.2f} m "
                "high; it takes off there and flies to the first waypoint at the survey's altitude, and after the "
                "loop back over it at that altitude to land (the plan says so)")


def material_m(world: World, xy_w: np.ndarray) -> np.ndarray:
    """The height of the material (pile) over each floor point (k, 2), by a ray straight down from under the roof."""
    top = world.storage.height_m - 1e-3
    o = np.column_stack([xy_w, np.full(len(xy_w), top)])
    d = np.tile([0.0, 0.0, -1.0], (len(xy_w), 1))
    r = world.cast(o, d, max_range_m=top + 1.0).range_m
    return np.where(np.isfinite(r), top - r, 0.0)


def footprint_w(xy_w: tuple[float, float], reach_m: float) -> np.ndarray:
    """The floor points a vehicle standing at xy_w covers, (k, 2): its centre and rings at half and full reach, every
    5 deg (3 cm apart at the F450's reach)."""
    a = np.radians(np.arange(0, 360, 5))
    rings = [np.column_stack([xy_w[0] + r * np.cos(a), xy_w[1] + r * np.sin(a)]) for r in (reach_m / 2, reach_m)]
    return np.vstack([np.asarray(xy_w, dtype=float)[None, :], *rings])


def takeoff_spot(mission: Mission, world: World) -> TakeoffSpot | None:
    """None when the floor below the first waypoint is clear (the vehicle takes off there, as before); else the clear
    floor point nearest to it, as an operator would choose: the material under the vehicle's footprint (`footprint_w`,
    its reach `f450_reach_m`) no higher than TAKEOFF_CLEAR_M, and the reach plus the mission's clearance from every
    wall. None too when no such point exists (material wall to wall): the caller then warns (`takeoff_under_pile`)."""
    w0 = np.asarray(mission.waypoints_w()[0], dtype=float)
    at_w0 = float(material_m(world, w0[None, :])[0])
    if at_w0 <= TAKEOFF_CLEAR_M:
        return None
    from scipy import ndimage
    s, reach = mission.storage, f450_reach_m()
    xs = np.arange(TAKEOFF_GRID_M / 2, s.length_m, TAKEOFF_GRID_M)
    ys = np.arange(TAKEOFF_GRID_M / 2, s.width_m, TAKEOFF_GRID_M)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    clear = (material_m(world, np.column_stack([gx.ravel(), gy.ravel()])) <= TAKEOFF_CLEAR_M).reshape(gx.shape)
    # Candidates: grid points whose grid neighbours within the footprint (and half a diagonal more) are clear; each
    # is then checked on its footprint itself, nearest first.
    k = math.ceil((reach + TAKEOFF_GRID_M / math.sqrt(2)) / TAKEOFF_GRID_M)
    disc = np.hypot(*np.mgrid[-k:k + 1, -k:k + 1]) * TAKEOFF_GRID_M <= reach + TAKEOFF_GRID_M / math.sqrt(2)
    clear = ndimage.binary_erosion(clear, structure=disc, border_value=1)
    margin = reach + mission.min_clearance_m
    clear &= (gx >= margin) & (gx <= s.length_m - margin) & (gy >= margin) & (gy <= s.width_m - margin)
    order = np.argsort(np.where(clear, np.hypot(gx - w0[0], gy - w0[1]), np.inf), axis=None)
    for i in order[:int(clear.sum())]:
        xy = (float(gx.flat[i]), float(gy.flat[i]))
        if (material_m(world, footprint_w(xy, reach)) <= TAKEOFF_CLEAR_M).all():
            return TakeoffSpot(xy, at_w0)
    return None


def takeoff_under_pile(mission: Mission, world: World) -> str | None:
    """A warning when the floor below the first waypoint, where the served vehicle waits when no clear take-off spot
    is found (`takeoff_spot`), lies under the pile: the simulator's vehicle then starts inside the material (the plant
    knows only the floor), and until it has climbed out the payload's samples see the pile from within."""
    x, y = (float(v) for v in mission.waypoints_w()[0])
    material = float(material_m(world, np.array([[x, y]]))[0])
    if material <= TAKEOFF_CLEAR_M:
        return None
    return (f"the vehicle waits on the floor below the first waypoint ({x:.1f}, {y:.1f}) m, where the pile stands "
            f"{material:.2f} m high, and no clear floor was found to take off from: in the simulator it starts inside "
            "the material, and the payload's samples see the pile from within until it has climbed out (a P_traj "
            "whose first corner is clear of the pile avoids it)")


def tlog_limits(max_mb: float) -> LinkLimits:
    """LinkLimits with the .tlog capped at max_mb megabytes (10^6 bytes); ValueError unless > 0."""
    if not (math.isfinite(max_mb) and max_mb > 0):
        raise ValueError(f"--tlog-max-mb must be > 0, got {max_mb:g}")
    return LinkLimits(tlog_max_bytes=max(1, round(max_mb * 1e6)))


def _serve(opts: ServeOptions, world: World | None, transport, folder: OutputFolder,
           spot: TakeoffSpot | None = None) -> int:
    cfg = opts.fly_config()
    mission, frame, out, kind = opts.mission, cfg.frame, opts.out, opts.vehicle
    pile = world.pile if world is not None else None
    origin = cfg.ekf_origin
    takeoff_w = spot.xy_w if spot is not None else None
    write_qgc_wpl(folder.staged(PLAN_FILE), mission, frame, origin.as_tuple(), takeoff_w=takeoff_w)
    plan = folder.publish(PLAN_FILE)
    if world is not None:
        pile.mesh.export(folder.staged(PILE_FILE))
        tfmini = {"rangefinder": opts.rangefinder.value} if opts.rangefinder is Rangefinder.TFMINI else {}
        truth = truth_record(pile, opts.stockpile, mission, frame, plant=kind, payload="networked",
                             seed=opts.faults.seed, faults=opts.faults, site=cfg.site, ekf_origin=origin,
                             **tfmini, **noise_header(cfg), **pose_error_header(cfg))
        if takeoff_w is not None:
            truth["takeoff_w"] = list(takeoff_w)  # where the vehicle waited: not below the first waypoint
        folder.staged(TRUTH_FILE).write_text(json.dumps(truth, indent=2) + "\n")
    vehicle = make_vehicle(kind, mission, frame, origin, takeoff_w)
    drift = make_drift(opts.pose_error, opts.faults.seed,
                       world_ground_below(world, frame) if world is not None else None)  # no pile: a bare floor
    if drift is not None:
        vehicle.attach_drift(drift)
        log.info("pose error: %s (the autopilot flies on, and reports, a drifting estimate; seed %d)",
                 opts.pose_error.value, opts.faults.seed)
    # The true and estimated trajectories for truth.json (as `fly` keeps them), on the simulator's clock: the
    # payload's log runs on its own, which `tools.fly_networked` aligns by the estimated trajectory.
    track: list[tuple[float, ...]] | None = [] if drift is not None and world is not None else None
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    devices = None
    try:
        if world is not None:
            devices = NetworkedDevices(vehicle, world, opts.devices_url, frame=frame,
                                       lever_arm_body_m=cfg.lever_arm_body_m,
                                       key=opts.signing.key if opts.signing is not None else None,
                                       rangefinder=opts.rangefinder)
        faults = NetworkedFaults(opts.faults, vehicle, transport, devices)
        if devices is not None:
            devices.start()
        signed = injected = ""
        if opts.signing is not None:
            signed = "; MAVLink signing on" + (" (unsigned frames accepted)" if opts.signing.allow_unsigned else "")
        if opts.faults.active:
            timed = any(n in PAIRS or n.endswith("_at_s") for n in opts.faults.active)
            injected = (f"; faults {', '.join(opts.faults.active)} (seed {opts.faults.seed}"
                        + ("; times count from the mission start)" if timed else ")"))
        log.info("serving a %s quadcopter on %s (listening at %s; %gx real time); site: %s; plan: %s%s%s%s", kind,
                 opts.url, _where(transport), opts.speedup, cfg.site.describe(), plan,
                 (f"; LiDAR and servo on {devices.url} (pile {opts.stockpile}, {pile.volume_m3:.1f} m^3)"
                  if devices else ""), signed, injected)
        if devices is not None:
            command = shlex.join(payload_command(opts, mavlink_at=_address(transport), devices_url=devices.url,
                                                 tfmini_path=devices.tfmini_path, run_dir=plan.parent))
            if devices.tfmini_path is not None:
                log.info("TFMini on %s: run the payload with: %s", devices.tfmini_path, command)
            else:
                log.info("run the payload with: %s", command)
        else:
            log.info("no payload: this run records no LiDAR data (for a survey, serve with --devices and run "
                     "pilescan-payload against it)")
        with MavlinkVehicleServer(vehicle, faults.transport, tlog_path=folder.staged(TLOG_FILE), home=origin,
                                  signing=opts.signing,
                                  extra_params=faults.params, limits=opts.limits) as server:
            faults.bind(server)
            noise = attach_sensor_noise(cfg.noise(), opts.faults.seed, server,
                                        devices.beam if devices is not None else None)
            if devices is not None:
                devices.attach_noise(noise)
            if cfg.noise().active:
                log.info("sensor noise: %s (%s)", cfg.sensor_noise, noise_summary(cfg.noise()))

            def on_step() -> None:
                if devices is not None:
                    devices.record()
                # twice truth.json's rate (not every physics step): a served session may run for hours
                if track is not None and (not track or vehicle.time_s() - track[-1][0] >= 0.5 / TRAJECTORY_RATE_HZ):
                    now = vehicle.state()
                    track.append((now.t_s, *now.pos_ned_m, now.yaw_rad, *vehicle.pose_error))
                faults.step()
            sim_s = run_realtime(server, vehicle, speedup=opts.speedup, duration_s=opts.duration_s, stop_event=stop,
                                 on_step=on_step)
    finally:
        if devices is not None:
            devices.close()
        transport.close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if track:
        a = np.array(track)
        traj = pose_error_truth(cfg, a[:, 0], a[:, 1:4], a[:, 4], a[:, 5:9], float(a[0, 0]), float(a[-1, 0]))
        traj[POSE_ERROR_KEY]["trajectory"]["clock"] = SIMULATOR_CLOCK
        truth.update(traj)
        # A served flight is not stopped at a wall (a real one would be): the approach is kept and a crash said.
        true_w = cfg.frame.ned_to_w(a[:, 1:4])
        approach = closest_approach(a[:, 0], true_w, cfg.mission.storage)
        truth["closest_approach"] = approach.to_dict() if approach is not None else None
        # and the pile (the vehicle takes off from floor clear of it: `takeoff_spot`)
        pile_near = f450_pile_approach(a[:, 0], true_w, world.heights_below_m)
        truth["closest_pile_approach"] = pile_near.to_dict() if pile_near is not None else None
        crash = collision(approach, f450_reach_m()) or pile_collision(pile_near)
        if crash is not None:
            log.warning("%s: a real flight would have ended there (the survey in %s is not one a vehicle could "
                        "have flown)", crash, out)
        folder.staged(TRUTH_FILE).write_text(json.dumps(truth, indent=2) + "\n")
    st = server.stats
    refused = ""
    if opts.signing is not None:
        refused = (f"; refused {st['rx_unsigned']} unsigned, {st['rx_bad_signature']} badly signed and "
                   f"{st['rx_replayed']} replayed frames")
    dropped = (f"; dropped {st['rx_datagrams_dropped']} malformed datagrams" if st["rx_datagrams_dropped"] else "")
    muted = f"; {st['statustext_dropped']} STATUSTEXT answers over the rate limit" if st["statustext_dropped"] else ""
    summary = faults.summary()
    unread = ""
    if devices is not None and devices.tfmini is not None and devices.tfmini.frames_dropped:
        unread = (f"; {devices.tfmini.frames_dropped} TFMini frames lost unread (nobody read its pseudo-terminal "
                  "and its buffer was full)")
    log.info("stopped after %.1f simulated seconds; telemetry in %s%s%s%s%s%s", sim_s, out / TLOG_FILE, refused,
             dropped, muted, unread, f"; faults: {summary}" if summary else "")
    return 0
