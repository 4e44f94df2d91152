"""Fly a mission in the SITL and write a run directory.

Run directory (DESIGN section 4): `samples.pslog` (sample log), `truth.json` (true volume, storage,
mission, seeds, energy, config), `pile.stl` (the stockpile mesh the LiDAR saw), `telemetry.tlog`
(the vehicle's MAVLink traffic, JSBSim plant) and `mission.waypoints` (the plan, QGC WPL 110).
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from firmware_py.core.cli import RunFailure, reading_input
from firmware_py.core.frames import StorageFrame
from firmware_py.core.header import build_log_header
from firmware_py.core.pose_source import HEADER_KEY as POSE_SOURCE_KEY
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
from firmware_py.core.samplelog import SampleLogWriter
from firmware_py.core.sensor import LIDARLITE_V3, Rangefinder, RangefinderSpec
from firmware_py.core.sensor_noise import HEADER_KEY as NOISE_HEADER_KEY
from firmware_py.core.sensor_noise import SensorNoise, SensorNoiseModel
from firmware_py.core.site import DEFAULT_SITE, GeodeticPoint, Site
from firmware_py.core.version import software_version
from firmware_py.core.waveform import Waveform, initial_position, named_waveform
from sitl.faults.injector import MOUNT_FAULTS, FaultSpec
from sitl.missions.coverage import LoopMission
from sitl.missions.qgc_wpl import write_qgc_wpl
from sitl.missions.range_check import RangeLimit, check_range
from sitl.missions.rectangle import Mission
from sitl.runners.flight import PAYLOAD_1D_KG, fly_mission
from sitl.sensing import pose_drift
from sitl.sensing.batch_sampler import sample_flight
from sitl.sensing.pose_drift import PoseErrorProfile
from sitl.vehicle.ideal_plant import IdealPlant, Trajectory
from sitl.world import stockpile as piles
from sitl.world.clearance import closest_approach, collision, f450_pile_approach, f450_reach_m, pile_collision
from sitl.world.raycast import World

log = logging.getLogger(__name__)

PLANTS = ("jsbsim", "ideal")
PAYLOADS = ("batch", "firmware")
LIDARLITE_FAULTS = frozenset({"i2c_nack_pct", "lidar_stuck_busy", "lidar_power_glitch_at_s", "lidar_garbage_pct"})
"""Faults of the LIDAR-Lite's I2C bus and registers: a TFMini has neither."""
TFMINI_FAULTS = frozenset({"tfmini_bad_frame_pct", "tfmini_garbage_pct", "tfmini_unplug"})
"""Faults of the TFMini's UART: a LIDAR-Lite has none."""


def check_rangefinder_faults(rangefinder: Rangefinder, faults: FaultSpec | None) -> None:
    """ValueError naming the first fault that acts on a part the flight does not carry."""
    for name in faults.active if faults is not None else ():
        if rangefinder is Rangefinder.TFMINI and name in LIDARLITE_FAULTS:
            raise ValueError(f"fault {name} acts on the LIDAR-Lite; this flight carries a TFMini")
        if rangefinder is Rangefinder.LIDARLITE_V3 and name in TFMINI_FAULTS:
            raise ValueError(f"fault {name} acts on the TFMini; fly it with --rangefinder tfmini")


@dataclass(frozen=True)
class FlyConfig:
    """Everything that defines a SITL survey flight."""

    mission: Mission = field(default_factory=Mission)
    stockpile: str = "1"
    waveform: str = "semi-triangular"
    servo_peak_rate_rad_s: float = 5.0
    initial_position: int = 0
    plant: str = "jsbsim"
    payload: str = "batch"
    latency_ms: tuple[float, float] = (0.0, 0.0)
    payload_kg: float = PAYLOAD_1D_KG
    seed: int = 0
    lever_arm_body_m: tuple[float, float, float] = (0.0, 0.0, 0.10)
    site: Site = DEFAULT_SITE
    """Where the building stands: its floor corner on Earth and the heading of its length (--origin, --heading)."""
    ekf_origin_at: GeodeticPoint | None = None
    """The autopilot's EKF origin (its home, the plant's reference, what the payload sends); None: the site's
    corner, as `pilescan-payload --origin` sends it."""
    lidar: RangefinderSpec = LIDARLITE_V3  # the datasheet flown (the rangefinder's, unless set)
    faults: FaultSpec | None = None  # fault injection (sitl.faults.injector), firmware payload only
    rangefinder: Rangefinder = Rangefinder.LIDARLITE_V3  # which part the payload drives (--rangefinder)
    sensor_noise: SensorNoiseModel = SensorNoiseModel.NONE  # firmware_py.core.sensor_noise; seeded by seed
    pose_error: PoseErrorProfile = PoseErrorProfile.NONE  # the indoor estimator flown on (sitl.sensing.pose_drift)

    def __post_init__(self) -> None:
        if not isinstance(self.rangefinder, Rangefinder):
            raise ValueError(f"rangefinder must be one of {', '.join(r.value for r in Rangefinder)}, "
                             f"got {self.rangefinder!r}")
        if self.rangefinder is not Rangefinder.LIDARLITE_V3 and self.lidar == LIDARLITE_V3:
            object.__setattr__(self, "lidar", self.rangefinder.spec)
        check_rangefinder_faults(self.rangefinder, self.faults)
        if self.plant not in PLANTS:
            raise ValueError(f"unknown plant {self.plant!r}; available: {', '.join(PLANTS)}")
        if self.payload not in PAYLOADS:
            raise ValueError(f"unknown payload {self.payload!r}; available: {', '.join(PAYLOADS)}")
        if self.faults is not None and not self.faults.mount_only and self.payload != "firmware":
            timed = [f for f in self.faults.active if f not in MOUNT_FAULTS]
            raise ValueError(f"fault {', '.join(timed)} needs the firmware payload (--payload firmware); the batch "
                             f"payload flies only the mounting's faults ({', '.join(sorted(MOUNT_FAULTS))})")
        if self.payload == "firmware" and self.plant != "jsbsim":
            raise ValueError("the firmware payload needs the jsbsim plant (it talks MAVLink to the vehicle)")
        lo, hi = self.latency_ms
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo <= hi <= 1000):
            raise ValueError(f"link latency must satisfy 0 <= min <= max <= 1000 ms, got {self.latency_ms}")
        initial_position(self.initial_position)  # validates the range
        if not (math.isfinite(self.payload_kg) and 0.0 <= self.payload_kg <= 2.0):
            raise ValueError(f"payload mass must be 0-2 kg, got {self.payload_kg}")
        if len(self.lever_arm_body_m) != 3 or not all(math.isfinite(v) for v in self.lever_arm_body_m):
            raise ValueError(f"lever arm must be 3 finite numbers, got {self.lever_arm_body_m}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"seed must be an integer >= 0, got {self.seed!r}")
        self.servo_waveform()  # validates the name and rate
        if not isinstance(self.site, Site):
            raise ValueError(f"site must be a Site, got {self.site!r}")
        if self.ekf_origin_at is not None and not isinstance(self.ekf_origin_at, GeodeticPoint):
            raise ValueError(f"EKF origin must be a GeodeticPoint, got {self.ekf_origin_at!r}")
        object.__setattr__(self, "sensor_noise", SensorNoiseModel(self.sensor_noise))
        self.noise()  # the rangefinder has a datasheet model
        try:
            object.__setattr__(self, "pose_error", PoseErrorProfile(self.pose_error))
        except ValueError:
            raise ValueError(f"pose error must be one of {', '.join(p.value for p in PoseErrorProfile)}, "
                             f"got {self.pose_error!r}") from None

    @property
    def ekf_origin(self) -> GeodeticPoint:
        """The local NED frame's origin on Earth: the vehicle's EKF origin and home, the plan's reference."""
        return self.ekf_origin_at if self.ekf_origin_at is not None else self.site.corner

    @property
    def frame(self) -> StorageFrame:
        """The storage frame W in the vehicle's local NED (the site about the EKF origin)."""
        return self.site.frame_about(self.ekf_origin)

    def noise(self) -> SensorNoise:
        """The sensor noise this flight carries, with its parameters for this rangefinder."""
        return SensorNoise.of(self.sensor_noise, self.lidar)

    def servo_waveform(self) -> Waveform:
        return named_waveform(self.waveform, self.servo_peak_rate_rad_s, self.initial_position)


@dataclass(frozen=True)
class RunResult:
    out_dir: Path
    n_samples: int
    duration_s: float
    true_volume_m3: float
    wall_time_s: float
    energy_j: float | None = None


def noise_header(cfg: FlyConfig) -> dict:
    """The header keys the flight's sensor noise adds: ``sensor_noise`` (none: nothing, the header as before)."""
    rec = cfg.noise().record()
    return {} if rec is None else {NOISE_HEADER_KEY: rec}


def pose_error_header(cfg: FlyConfig) -> dict:
    """The header keys the flight's pose-error profile adds: ``pose_error`` (none: nothing)."""
    rec = pose_drift.record(cfg.pose_error, cfg.seed)
    return {} if rec is None else {pose_drift.HEADER_KEY: rec}


def log_header(cfg: FlyConfig, wf: Waveform) -> dict:
    """The sample-log header of a SITL flight: what the ground station needs to place the points. The autopilot's
    EKF source parameters are the ones the simulated autopilot serves for the flight's profile, which the payload
    reads over MAVLink in a firmware flight (`firmware_py.core.pose_source`)."""
    return build_log_header(source=f"sitl/{cfg.plant}", sensor=cfg.lidar.to_dict(),
                            lever_arm_body_m=cfg.lever_arm_body_m, waveform_name=cfg.waveform, waveform=wf,
                            initial_position=cfg.initial_position, storage=cfg.mission.storage, frame=cfg.frame,
                            mission_id=cfg.mission.mission_id, mission=cfg.mission.to_dict(), site=cfg.site,
                            extra={**noise_header(cfg), **pose_error_header(cfg),
                                   POSE_SOURCE_KEY: pose_drift.ekf_source_params(cfg.pose_error)})


def check_clearance(mission: Mission, pile: piles.Stockpile,
                    pose_error: PoseErrorProfile = PoseErrorProfile.NONE) -> None:
    """Refuse a flight that would hit the stockpile, or the roof: an autopilot whose altitude follows a
    downward rangefinder (`flow`) climbs over the pile by the rangefinder's weight times its height."""
    top = pile.max_height_m
    if mission.altitude_m - top < mission.min_clearance_m:
        raise ValueError(f"altitude {mission.altitude_m:g} m is too low: the stockpile top is at {top:.2f} m "
                         f"(clearance {mission.min_clearance_m:g} m needed)")
    p = pose_drift.profile_params(pose_error)
    climb = 0.0 if p is None else p.rangefinder_weight * top
    roof = mission.storage.height_m
    if climb > 0 and mission.altitude_m + climb > roof - mission.min_clearance_m:
        raise ValueError(f"altitude {mission.altitude_m:g} m is too high for --pose-error {pose_error.value}: over "
                         f"the {top:.2f} m pile the vehicle climbs {climb:.2f} m (its rangefinder height), to within "
                         f"{roof - mission.altitude_m - climb:.2f} m of the {roof:g} m roof "
                         f"({mission.min_clearance_m:g} m clearance needed)")


def drift_warning(mission: Mission | LoopMission, pose_error: PoseErrorProfile) -> str | None:
    """A warning when the estimate a vehicle flies on can drift further than its legs keep from the walls: the
    profile's velocity scale and drift errors, as fractions of the distance flown, against the legs' distance
    from the nearest wall less the vehicle's reach (a flight that reaches a wall fails, `sitl.world.clearance`).
    Any mission (the rectangle's or a planned loop): the legs are straight between waypoints, so their nearest
    approach to a wall is at a waypoint."""
    p = pose_drift.profile_params(pose_error)
    if p is None:
        return None
    margin = legs_room_m(mission)
    path = mission.path_length_m()
    drift = (p.scale_sigma_rel + p.drift_rel) * path
    room = margin - f450_reach_m()
    if drift <= room:
        return None
    remedy = "a larger P_traj keeps" if isinstance(mission, Mission) else "legs further from the walls keep"
    return (f"the legs run {margin:.2f} m from the walls, and a {pose_error.value} estimate can drift "
            f"{(p.scale_sigma_rel + p.drift_rel) * 100:.1f} % of the {path:.0f} m flown ({drift:.1f} m): the vehicle "
            f"may reach a wall ({remedy} it further off)")


def legs_room_m(mission: Mission | LoopMission) -> float:
    """The legs' nearest approach to a wall (m): the least distance of a waypoint from the four walls."""
    s, wp = mission.storage, mission.waypoints_w()
    return float(np.min(np.minimum.reduce([wp[:, 0], s.length_m - wp[:, 0], wp[:, 1], s.width_m - wp[:, 1]])))


TRAJECTORY_RATE_HZ = 10.0
"""Rate of the true trajectory truth.json keeps with a pose-error profile."""


def pose_error_truth(cfg: FlyConfig, t_s: np.ndarray, pos_ned_m: np.ndarray, yaw_rad: np.ndarray,
                     error: np.ndarray, t_start_s: float, t_end_s: float) -> dict:
    """truth.json's ``pose_error``: the profile and seed, the error's statistics over the survey and the
    true and estimated trajectories at TRAJECTORY_RATE_HZ (storage frame W, m; yaw as MAVLink's, NED, rad)."""
    rec = pose_drift.record(cfg.pose_error, cfg.seed)
    if rec is None:
        return {}
    t = np.asarray(t_s, dtype=float)
    survey = (t >= t_start_s - 1e-9) & (t <= t_end_s + 1e-9)
    grid = np.arange(t_start_s, t_end_s + 1e-9, 1.0 / TRAJECTORY_RATE_HZ)
    at = lambda col: np.interp(grid, t, col)  # noqa: E731
    pos = np.column_stack([at(pos_ned_m[:, j]) for j in range(3)])
    err = np.column_stack([at(error[:, j]) for j in range(4)])
    yaw_u = at(np.unwrap(yaw_rad))
    wrap = lambda a: (a + np.pi) % (2 * np.pi) - np.pi  # noqa: E731
    true_w, est_w = cfg.frame.ned_to_w(pos), cfg.frame.ned_to_w(pos + err[:, :3])
    rnd = lambda a: np.round(a, 4).tolist()  # noqa: E731
    return {pose_drift.HEADER_KEY: {
        **rec, "stats": pose_drift.error_stats(error[survey]),
        "trajectory": {"rate_hz": TRAJECTORY_RATE_HZ, "frame": "storage W (m); yaw NED (rad)",
                       "t_s": rnd(grid), "true_w_m": rnd(true_w), "true_yaw_rad": rnd(wrap(yaw_u)),
                       "estimated_w_m": rnd(est_w), "estimated_yaw_rad": rnd(wrap(yaw_u + err[:, 3]))}}}


def make_pose_drift(cfg: FlyConfig, world: World) -> pose_drift.PoseDrift | None:
    """The flight's estimator error (None: `none`), its rangefinder looking down into `world`."""
    return pose_drift.make_drift(cfg.pose_error, cfg.seed, pose_drift.world_ground_below(world, cfg.frame))


def truth_record(pile: piles.Stockpile, stockpile: str, mission: Mission, frame: StorageFrame, *, plant: str,
                 payload: str, seed: int, faults: FaultSpec | None = None, site: Site | None = None,
                 ekf_origin: GeodeticPoint | None = None, **flight) -> dict:
    """truth.json: what the ground station checks a survey against (the world, the mission, the faults,
    how it was flown); `flight` adds what the flight gave (flight time, energy, samples ...).
    Written by `fly` and by `serve --devices` (payload "networked")."""
    return {
        "true_volume_m3": pile.volume_m3,
        "stockpile": stockpile,
        "stockpile_source": pile.source,
        "pile_seed": piles.PAPER_PILES.get(stockpile, {}).get("seed"),
        "seed": seed,
        "storage": mission.storage.to_dict(),
        "storage_frame": frame.to_dict(),
        "site": site.to_dict() if site is not None else None,
        "ekf_origin": dict(zip(("lat_deg", "lon_deg", "alt_m"), ekf_origin.as_tuple(), strict=True))
        if ekf_origin is not None else None,
        "mission": mission.to_dict(),
        "mission_id": mission.mission_id,
        "plant": plant,
        "payload": payload,
        "faults": faults.to_dict() if faults is not None and faults.active else None,
        **flight,
        "software": software_version(),
    }


def fly(cfg: FlyConfig, out_dir: str | Path, force: bool = False,
        progress: Callable[[str], None] | None = None) -> RunResult:
    """Fly cfg with the selected plant and write the run directory (`firmware_py.core.rundir.OutputFolder`:
    locked while written, refused when it holds another run unless force, truth.json put in place last).

    Progress goes to `progress`, or to this module's logger (info) when it is None.
    """
    t0 = time.perf_counter()
    say = progress or log.info
    out = check_free(out_dir, RUN_FILES, force=force)  # refuse a taken --out before any work
    storage = cfg.mission.storage
    with reading_input("--stockpile"):
        pile = piles.resolve(cfg.stockpile, storage)
    check_clearance(cfg.mission, pile, cfg.pose_error)
    drift = drift_warning(cfg.mission, cfg.pose_error)
    if drift:
        log.warning(drift)
    wf = cfg.servo_waveform()
    out_of_range = check_range(cfg.mission, RangeLimit(cfg.lidar.max_range_m, cfg.noise().returns, cfg.lidar.model),
                               wf, cfg.lever_arm_body_m)
    if out_of_range:
        log.warning(out_of_range)
    with OutputFolder(out, RUN_FILES, TRUTH_FILE, force=force) as folder:
        log.debug("%s locked; files are written in %s and put in place when the flight ends", out, folder.staging)
        say(f"stockpile: {pile.source}, true volume {pile.volume_m3:.1f} m^3")
        say(f"flying {cfg.mission.path_length_m():.0f} m with the {cfg.plant} plant, {cfg.payload} payload"
            + (f", {cfg.sensor_noise} sensor noise" if cfg.noise().active else "")
            + (f", flying on a {cfg.pose_error.value} pose estimate" if cfg.pose_error is not PoseErrorProfile.NONE
               else ""))
        log_path, tlog_path = folder.staged(SAMPLES_FILE), folder.staged(TLOG_FILE)
        if cfg.payload == "firmware":
            from sitl.runners.lockstep_payload import fly_firmware
            run = fly_firmware(cfg, log_path, log_header(cfg, wf), latency_ms=cfg.latency_ms, tlog_path=tlog_path,
                               seed=cfg.seed, faults=cfg.faults)
            if run.faults and run.faults.get("power_cut"):
                say(f"power cut at {cfg.faults.power_cut_at_s:g} s: the log holds the blocks written by then")
            elif not run.completed:
                raise RunFailure(f"the vehicle did not complete the mission within {run.duration_s:.0f} s")
            if cfg.faults is not None and cfg.faults.active:
                say(f"faults injected: {', '.join(cfg.faults.active)}")
            records, duration_s, energy_j = run.records, run.duration_s, run.energy_j
            t_true, w_true = run.true_t_s, cfg.frame.ned_to_w(_ned(run.true_states))
            approach = closest_approach(t_true, w_true, storage)
            world = run.world  # the flight's own, for the pile's clearance below
            pose_truth = {}
            if run.true_pose_error is not None:
                t_end = float(run.true_t_s[-1])
                pose_truth = pose_error_truth(cfg, run.true_t_s, _ned(run.true_states), run.true_states["yaw_rad"],
                                              run.true_pose_error, t_end - duration_s, t_end)
        else:
            world = World(storage, pile, max_range_m=cfg.lidar.max_range_m)
            flown = fly_trajectory(cfg, tlog_path, world)
            traj, duration_s, energy_j = flown.trajectory, flown.duration_s, flown.energy_j
            t_true, w_true = traj.t_s, cfg.frame.ned_to_w(traj.pos_ned_m)
            approach = closest_approach(t_true, w_true, storage)
            mount = cfg.faults or FaultSpec()
            records = sample_flight(traj, wf, world, cfg.lidar, cfg.lever_arm_body_m, cfg.frame,
                                    noise=cfg.noise(), seed=cfg.seed, pose_error=flown.pose_error,
                                    servo_gain=mount.servo_gain, servo_offset_rad=mount.servo_offset_rad,
                                    boresight=mount.boresight)
            if mount.active:
                say(f"faults injected: {', '.join(mount.active)}")
            pose_truth = {} if flown.truth is None else pose_error_truth(cfg, *flown.truth, 0.0, duration_s)
            # The batch path writes a finished flight at once: the commit's fsync is enough.
            with SampleLogWriter(log_path, log_header(cfg, wf), records_per_block=500, fsync=False) as w:
                w.append(records)
        # And the pile, over the survey (a lockstep flight starts below its first waypoint, which may be in a pile)
        surveying = np.asarray(t_true, dtype=float) >= float(t_true[-1]) - duration_s
        pile_near = f450_pile_approach(np.asarray(t_true)[surveying], np.asarray(w_true)[surveying],
                                       world.heights_below_m)
        crash = collision(approach, f450_reach_m())
        if crash is not None:
            # A real flight ends there; the physics here would fly on through the wall. No survey is written.
            raise RunFailure(f"{crash}" + (f" (it flew on a {cfg.pose_error.value} pose estimate, which drifts: fly "
                                          "with more room from the walls, a larger P_traj, or a better estimate)"
                                          if cfg.pose_error is not PoseErrorProfile.NONE else ""))
        crash = pile_collision(pile_near)
        if crash is not None:  # as through a wall
            raise RunFailure(f"{crash}: fly higher over it" + (
                f" (it flew on a {cfg.pose_error.value} pose estimate, whose altitude reference drifts)"
                if cfg.pose_error is not PoseErrorProfile.NONE else ""))
        pile.mesh.export(folder.staged(PILE_FILE))
        write_qgc_wpl(folder.staged(PLAN_FILE), cfg.mission, cfg.frame, cfg.ekf_origin.as_tuple())
        truth = truth_record(pile, cfg.stockpile, cfg.mission, cfg.frame, plant=cfg.plant, payload=cfg.payload,
                             seed=cfg.seed, faults=cfg.faults, site=cfg.site, ekf_origin=cfg.ekf_origin,
                             flight_time_s=duration_s, energy_j=energy_j,
                             payload_kg=cfg.payload_kg if cfg.plant == "jsbsim" else None, n_samples=len(records),
                             servo_initial_position=cfg.initial_position, waveform=cfg.waveform,
                             **({"rangefinder": cfg.rangefinder.value}
                                if cfg.rangefinder is Rangefinder.TFMINI else {}),
                             closest_approach=approach.to_dict() if approach is not None else None,
                             closest_pile_approach=pile_near.to_dict() if pile_near is not None else None,
                             **noise_header(cfg), **pose_truth)
        folder.staged(TRUTH_FILE).write_text(json.dumps(truth, indent=2) + "\n")
        folder.commit()
    n_ret = int(np.count_nonzero(records["flags"] == 0))
    say(f"wrote {out}: {len(records)} samples ({n_ret} returns), {duration_s:.0f} s flight"
        + (f", {energy_j / 1000:.1f} kJ" if energy_j is not None else ""))
    return RunResult(out, len(records), duration_s, pile.volume_m3, time.perf_counter() - t0, energy_j)


def _ned(states: np.ndarray) -> np.ndarray:
    return np.column_stack([states["north_m"], states["east_m"], states["down_m"]])


@dataclass(frozen=True)
class FlownTrajectory:
    """A batch flight: the true trajectory at the LiDAR's sample times, the estimator's error there (None:
    flown on the truth), and the finer record truth.json keeps (t, NED position, yaw, error; None: none)."""

    trajectory: Trajectory
    duration_s: float
    energy_j: float | None
    pose_error: np.ndarray | None = None
    truth: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None


IDEAL_ESTIMATE_STEP_S = 0.02
"""Step of the ideal plant flown on an estimate (the estimator's update rate there: 50 Hz)."""


def fly_ideal_on_estimate(plant: IdealPlant, t_s: np.ndarray, drift: pose_drift.PoseDrift,
                          step_s: float = IDEAL_ESTIMATE_STEP_S) -> tuple[Trajectory, np.ndarray, tuple]:
    """The ideal plant with an autopilot that flies the plan exactly in its estimate: the true pose is the
    plan minus the estimator's error (taken one step back: the controller acts on the last estimate).
    Returns the true trajectory and the error at t_s, and the (t, NED, yaw, error) record on the step grid."""
    grid = np.arange(0.0, plant.duration_s + step_s, step_s)
    plan = plant.states(grid)
    err = np.zeros((len(grid), 4))
    pos = np.empty((len(grid), 3))
    e = pose_drift.ZERO
    for k in range(len(grid)):
        p = plan.pos_ned_m[k] - np.asarray(e[:3])
        e = drift.update(float(grid[k]), (p[0], p[1], p[2]))
        pos[k], err[k] = p, e
    yaw = plan.yaw_rad - np.r_[0.0, err[:-1, 3]]
    at = lambda col: np.interp(t_s, grid, col)  # noqa: E731
    yaw_u = np.unwrap(yaw)
    ref = plant.states(t_s)
    traj = Trajectory(np.asarray(t_s, dtype=float), np.column_stack([at(pos[:, j]) for j in range(3)]),
                      ref.roll_rad, ref.pitch_rad, (at(yaw_u) + np.pi) % (2 * np.pi) - np.pi)
    return traj, np.column_stack([at(err[:, j]) for j in range(4)]), (grid, pos, yaw, err)


def fly_trajectory(cfg: FlyConfig, tlog_path: Path | None = None, world: World | None = None) -> FlownTrajectory:
    """The flown trajectory at the LiDAR's sample times, the flight time and the energy (None: ideal).

    With tlog_path, the JSBSim vehicle's MAVLink telemetry is logged there (the ideal plant has none).
    With a pose-error profile (`cfg.pose_error`) the vehicle flies on its estimate (`world`: what its
    downward rangefinder sees; None: a bare floor).
    """
    drift = make_pose_drift(cfg, world) if world is not None else pose_drift.make_drift(cfg.pose_error, cfg.seed)
    if cfg.plant == "ideal":
        plant = IdealPlant(cfg.mission, cfg.frame)
        t = plant.sample_times(cfg.lidar.rate_hz)
        if drift is None:
            return FlownTrajectory(plant.states(t), plant.duration_s, None)
        traj, err, rec = fly_ideal_on_estimate(plant, t, drift)
        return FlownTrajectory(traj, plant.duration_s, None, err, rec)
    flown = fly_mission(cfg.mission, cfg.frame, payload_kg=cfg.payload_kg, tlog_path=tlog_path,
                        origin=cfg.ekf_origin, drift=drift)
    if not flown.completed:
        raise RunFailure(f"the vehicle did not complete the mission within {flown.duration_s:.0f} s "
                         f"(reached {len(flown.reached)} of {len(cfg.mission.waypoints_w()) - 1} waypoints)")
    t = np.arange(int(flown.duration_s * cfg.lidar.rate_hz) + 1) / cfg.lidar.rate_hz
    truth = None if flown.pose_error is None else (flown.t_s, _ned(flown.states), flown.states["yaw_rad"],
                                                     flown.pose_error)
    return FlownTrajectory(flown.trajectory_at(t), flown.duration_s, flown.energy_j, flown.pose_error_at(t), truth)
