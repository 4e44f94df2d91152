"""`pilescan-sitl`: fly survey missions in the software-in-the-loop simulator.

fly    lockstep, as fast as the CPU allows, writing a run directory;
serve  the vehicle as a MAVLink autopilot on UDP, in real time (or N x), for MAVProxy, QGC, the payload;
plan   export the survey as a QGC WPL 110 mission file.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import time
from collections.abc import Sequence
from pathlib import Path

from firmware_py.core.cli import (
    ArgumentParser,
    ConfigTables,
    RunFailure,
    UserError,
    add_config_option,
    add_verbosity,
    finite_float,
    rangefinder_arg,
    reading_input,
    run_cli,
)
from firmware_py.core.rundir import publish_file
from firmware_py.core.sensor import Rangefinder
from firmware_py.core.sensor_noise import SensorNoiseModel
from firmware_py.core.site import DEFAULT_SITE, Site, add_site_options, site_from_args
from firmware_py.core.storage import Storage
from firmware_py.core.version import software_version
from firmware_py.core.waveform import N_PHASES, Waveform, named_waveform
from sitl.faults.injector import MOUNT_FAULTS, FaultSpec, fault_syntax
from sitl.missions.coverage import DEFAULT_SEEN_RADIUS_M, WALLS
from sitl.missions.gaps import DEFAULT_GAP_TARGET_PCT
from sitl.missions.qgc_wpl import write_qgc_wpl
from sitl.missions.rectangle import TURN_MODES, Mission
from sitl.runners.fly import PAYLOADS, PLANTS, FlyConfig, drift_warning, fly
from sitl.sensing.pose_drift import PoseErrorProfile

log = logging.getLogger(__name__)

MISSION_KINDS = ("rectangle", "coverage", "fill-gaps")
_SITE_AND_MISSION = {
    "site.dimensions": "--storage",
    "site.origin": "--origin",
    "site.heading_deg": "--heading",
    "mission.p_traj_pct": "--p-traj",
    "mission.altitude_m": "--altitude",
    "mission.speed_m_s": "--speed",
    "mission.yaw_rate_max_deg_s": "--yaw-rate-max",
    "mission.turn": "--turn",
}
CONFIG_OPTIONS: ConfigTables = {
    "fly": {**_SITE_AND_MISSION,
            "payload.rangefinder": "--rangefinder",
            "payload.sweep.waveform": "--waveform",
            "payload.sweep.peak_rate_rad_s": "--servo-rate",
            "payload.sweep.phase": "--phase",
            "sitl.sensor_noise": "--sensor-noise",
            "sitl.pose_error": "--pose-error"},
    "serve": {**_SITE_AND_MISSION,
              "payload.rangefinder": "--rangefinder",
              "payload.signing_key": "--signing-key",
              "sitl.sensor_noise": "--sensor-noise",
              "sitl.pose_error": "--pose-error"},
    "plan": {**_SITE_AND_MISSION,
             "sitl.pose_error": "--pose-error"},
}
"""Configuration key -> the option it sets, per subcommand (`firmware_py.core.cli.apply_config`;
docs/configuration.md). serve's --mavlink is where the vehicle listens, not the payload's link, so
[payload] mavlink does not map to it."""


def build_parser() -> ArgumentParser:
    ap = ArgumentParser(prog="pilescan-sitl", description=__doc__)
    ap.add_argument("--version", action="version", version=software_version())
    add_verbosity(ap)
    add_config_option(ap)
    sub = ap.add_subparsers(dest="command", required=True, parser_class=ArgumentParser)
    f = sub.add_parser("fly", help="fly a survey and write a run directory")
    f.add_argument("--stockpile", required=True, help="1, 2 (the paper's piles) or an STL/OBJ mesh path")
    _mission_options(f, p_traj_required=True)
    _sweep_options(f)
    _coverage_options(f, fly=True)
    f.add_argument("--phase", type=int, default=0, metavar="K",
                   help=f"servo initial position 0..{2 * N_PHASES - 1} (Fig. 9: {N_PHASES} phases x 2 "
                        f"directions; K >= {N_PHASES} sweeps the other way)")
    f.add_argument("--plant", choices=PLANTS, default="jsbsim",
                   help="vehicle: jsbsim (F450 flight dynamics + autopilot, default) or ideal (kinematic)")
    f.add_argument("--payload", choices=PAYLOADS, default=None,
                   help="firmware: the unchanged payload firmware in the loop over MAVLink and emulated I2C/PWM "
                        "devices (default with --plant jsbsim); batch: the vectorised sampler (fast; the default "
                        "with --plant ideal, which has no autopilot to talk to)")
    _rangefinder_options(f)
    f.add_argument("--latency-ms", type=finite_float, nargs=2, default=(0.0, 0.0), metavar=("MIN", "MAX"),
                   help="firmware payload only: random MAVLink latency range, ms")
    f.add_argument("--payload-mass", type=finite_float, default=0.040, metavar="KG",
                   help="payload mass, kg (0.040: LIDAR-Lite + servo; 0.370 2D LiDAR; 0.830 3D)")
    f.add_argument("--fault", action="append", default=[], metavar="NAME=VALUE",
                   help=f"inject a fault (repeatable): {fault_syntax()} (the firmware payload flies every one, the "
                        f"batch payload the mounting's: {fault_syntax(sorted(MOUNT_FAULTS))}; the tfmini_* ones with "
                        "--rangefinder tfmini; tfmini_unplug's DURATION inf: for good; times from the survey start; "
                        "seeded by --seed; docs/reliability.md says what each does)")
    _noise_option(f)
    _pose_error_option(f)
    f.add_argument("--seed", type=int, default=0, help="seed of the run's random draws (sensor noise included)")
    f.add_argument("--out", required=True, help="run directory to write")
    f.add_argument("--force", action="store_true",
                   help="replace a run already in --out (its files are removed, truth.json first, before flying)")
    add_verbosity(f, sub=True, quiet_help="print nothing but warnings and errors")
    add_config_option(f, sub=True)

    sv = sub.add_parser("serve", help="run the vehicle as a MAVLink autopilot on a network link, in real time")
    sv.add_argument("--mavlink", default="udp:127.0.0.1:14550",
                    help="where to serve: udp:HOST:PORT listens (clients use udpout:HOST:PORT), "
                         "udpout:HOST:PORT sends to a fixed peer (default udp:127.0.0.1:14550)")
    sv.add_argument("--speedup", type=finite_float, default=1.0, help="simulated seconds per wall second")
    sv.add_argument("--duration", type=finite_float, default=None, metavar="S",
                    help="stop after S simulated seconds (default: run until Ctrl-C / SIGTERM)")
    sv.add_argument("--vehicle", choices=("jsbsim", "kinematic"), default="jsbsim")
    sv.add_argument("--devices", default=None, metavar="tcp:HOST:PORT",
                    help="also serve the emulated LIDAR-Lite (I2C 0x62) and servo (PWM channel 0) there, for "
                         "`pilescan-payload --hal sitl:HOST:PORT` in another process (needs --speedup 1)")
    sv.add_argument("--stockpile", default="1", help="with --devices: 1, 2 or an STL/OBJ mesh path (default 1)")
    _rangefinder_options(sv)  # with --devices: tfmini also streams on a pseudo-terminal, its path printed
    _mission_options(sv, p_traj_required=False)
    sv.add_argument("--out", default="runs/serve",
                    help="run directory for mission.waypoints (at once), telemetry.tlog and, with --devices, "
                         "pile.stl and truth.json (when it stops); default runs/serve")
    sv.add_argument("--force", action="store_true",
                    help="replace a run already in --out (its files are removed, truth.json first)")
    add_verbosity(sv, sub=True)
    add_config_option(sv, sub=True)
    sv.add_argument("--signing-key", default=None, metavar="FILE",
                    help="MAVLink 2 signing key file (64 hex digits, or a passphrase line: key = its SHA-256, as "
                         "MAVProxy's 'signing setup'; chmod 600): sign everything, refuse unsigned, forged and "
                         "replayed frames; only clients that sent a signed frame are answered; with --devices the key "
                         "also authenticates the device bridge")
    sv.add_argument("--allow-unsigned", action="store_true",
                    help="with --signing-key: also accept unsigned frames (mixed setups)")
    sv.add_argument("--fault", action="append", default=[], metavar="NAME=VALUE",
                    help="inject a fault (repeatable; the names of fly's --fault): link_loss_pct=10, link_dup_pct, "
                         "link_reorder_pct, link_outage=START,DUR, link_latency_ms, link_jitter_ms, "
                         "autopilot_reboot=AT,SILENT_S; with --devices also i2c_nack_pct, lidar_stuck_busy=START,DUR, "
                         "lidar_power_glitch_at_s, lidar_garbage_pct, lidar_glitch_pct, servo_stuck_at_s, "
                         "servo_slow_factor, servo_delay_ms. Times count from the mission start (AUTO); the "
                         "SIM_PS_* parameters change faults while it runs")
    _noise_option(sv)
    _pose_error_option(sv)
    sv.add_argument("--seed", type=int, default=0, help="seed of the fault and sensor-noise draws (default 0)")
    sv.add_argument("--tlog-max-mb", type=finite_float, default=256.0, metavar="MB",
                    help="cap on telemetry.tlog in megabytes (default 256: about half a day of telemetry); "
                         "once reached, one warning and nothing more is logged")

    pl = sub.add_parser("plan", help="export the survey as a QGC WPL 110 mission (.waypoints)")
    _mission_options(pl, p_traj_required=True)
    _coverage_options(pl, fly=False)
    _sweep_options(pl)
    _rangefinder_options(pl)
    _noise_option(pl)
    _pose_error_option(pl, plan=True)
    pl.add_argument("--out", required=True, help="plan file to write (.waypoints)")
    pl.add_argument("--force", action="store_true", help="replace the plan file if it exists")
    add_verbosity(pl, sub=True)
    add_config_option(pl, sub=True)
    return ap


def _sweep_options(p: ArgumentParser) -> None:
    p.add_argument("--waveform", choices=("semi-triangular", "sinusoidal"), default="semi-triangular",
                   help="servo waveform (eq. 1; C=0.95 or C=0)")
    p.add_argument("--servo-rate", type=finite_float, default=5.0,
                   help="peak servo rate, rad/s (sets f; default 5 -> 0.67 Hz semi-triangular)")


def _coverage_options(p: ArgumentParser, fly: bool) -> None:
    if fly:
        p.add_argument("--mission", choices=MISSION_KINDS, default="rectangle",
                       help="rectangle: the paper's (--p-traj, --turn); coverage: the least-energy loop the coverage "
                            "planner finds for --coverage (docs/coverage.md); fill-gaps: a short re-flight over what "
                            "the report --fill-gaps could not see")
    p.add_argument("--coverage", type=finite_float, default=None, metavar="PCT",
                   help="plan for this predicted floor coverage R_a, percent (the coverage planner: per-wall offsets, "
                        "corner cuts, speed up to 2 m/s; --p-traj, --turn and --speed are then not used)")
    p.add_argument("--seen-radius", type=finite_float, default=DEFAULT_SEEN_RADIUS_M, metavar="M",
                   help="with --coverage: a floor cell counts as seen when a return lies this near (default "
                        f"{DEFAULT_SEEN_RADIUS_M:g} m)")
    p.add_argument("--surface", default=None, metavar="REPORT_DIR",
                   help="with --coverage: plan on an earlier survey's surface (the report directory's surface.npz "
                        "and cloud.ply): beams stop at the piles it measured, and the floor it did not see must "
                        "still be seen (default: the empty floor)")
    p.add_argument("--bare-walls", action="store_true",
                   help="with --coverage: count the floor up to every wall (default: plan for material leaning on "
                        "any wall, whose points within the report's wall band are taken for the wall: legs near "
                        "enough to see every wall's foot steeply)")
    p.add_argument("--fill-gaps", default=None, metavar="REPORT_DIR",
                   help="plan a short re-flight over the floor this report could not see (its unseen cells: legs whose "
                        "fans the coverage model predicts to cover them, least energy)" + (
                            " (with --mission fill-gaps)" if fly else "") + "; merge the two logs with "
                        "`pilescan-ground report RUN1 RUN2 --out DIR`")
    p.add_argument("--gap-coverage", type=finite_float, default=DEFAULT_GAP_TARGET_PCT, metavar="PCT",
                   help="with --fill-gaps: the share of the unseen cells the re-flight must be predicted to cover "
                        f"(default {DEFAULT_GAP_TARGET_PCT:g} %%)")
    p.add_argument("--all-phases", action="store_true",
                   help=f"with --coverage: plan for the worst of all {2 * N_PHASES} servo start positions, not only "
                        + ("--phase" if fly else "position 0")
                        + " (a plan that holds whatever position the servo starts in; up to 20 times the planning "
                          "time)")


def _rangefinder_options(p: ArgumentParser) -> None:
    p.add_argument("--rangefinder", type=rangefinder_arg, default=Rangefinder.LIDARLITE_V3,
                   metavar="|".join(r.value for r in Rangefinder),
                   help="the payload's rangefinder: lidarlite-v3 (I2C, 500 Hz, 40 m; default) or tfmini (Benewake "
                        "TFmini-S on a UART, 100 Hz, 12 m: fly lower, see the README)")


def _sensor_noise(text: str) -> SensorNoiseModel:
    try:
        return SensorNoiseModel(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"must be one of {', '.join(m.value for m in SensorNoiseModel)}, got {text!r}") from None


def _noise_option(p: ArgumentParser) -> None:
    p.add_argument("--sensor-noise", type=_sensor_noise, default=SensorNoiseModel.NONE,
                   metavar="{" + ",".join(m.value for m in SensorNoiseModel) + "}",
                   help="sensor noise: none (ideal, default); datasheet (the rangefinder's datasheet: range noise "
                        "sigma = max(abs, rel x r), bias, quantum, no-returns near its rated range at low reflectance "
                        "and grazing incidence); appendix-a (the paper's: range 2.5 cm, servo 1 deg, attitude "
                        "0.143 deg, position 0.113 m). Recorded in the log header; seeded by --seed "
                        "(docs/sensor_noise.md)")


def _pose_error(text: str) -> PoseErrorProfile:
    try:
        return PoseErrorProfile(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"must be one of {', '.join(m.value for m in PoseErrorProfile)}, got {text!r}") from None


def _pose_error_option(p: ArgumentParser, plan: bool = False) -> None:
    metavar = "{" + ",".join(m.value for m in PoseErrorProfile) + "}"
    if plan:
        p.add_argument("--pose-error", type=_pose_error, default=PoseErrorProfile.NONE, metavar=metavar,
                       help="the indoor pose estimate the vehicle will fly the plan on: flow (optical flow + downward "
                            "rangefinder, drifting ~4%% of the distance with its scale error) or vio (visual "
                            "odometry, ~1.5%%); warns when it can drift further than the legs keep from the walls "
                            "(default none: motion capture or RTK, no warning; docs/pose_error.md)")
        return
    p.add_argument("--pose-error", type=_pose_error, default=PoseErrorProfile.NONE, metavar=metavar,
                   help="the indoor pose estimate the autopilot flies on and reports in ATTITUDE and "
                        "LOCAL_POSITION_NED: none (the truth, default); flow (optical flow + downward rangefinder: "
                        "drift ~2%% of the distance, heading drift, baro drift, and an altitude that follows the pile "
                        "below); vio (visual odometry: drift ~1%% of the distance, heading and baro drift). The true "
                        "trajectory goes into truth.json; the profile into the log header; seeded by --seed "
                        "(docs/pose_error.md)")


def _mission_options(p: ArgumentParser, p_traj_required: bool) -> None:
    p.add_argument("--p-traj", type=finite_float, default=None if p_traj_required else 20.0,
                   metavar="PCT", help="waypoint offset from the walls, percent of L and W (eqs. 17-18), 0-50"
                   + (" (the rectangle mission needs it)" if p_traj_required else ""))
    p.add_argument("--storage", default="60x40x15", help="building LxWxH in metres (default 60x40x15)")
    p.add_argument("--turn", choices=TURN_MODES, default="one-step", help="corner turns (Fig. 15)")
    p.add_argument("--speed", type=finite_float, default=1.0, help="flight speed, m/s (default 1.0)")
    p.add_argument("--altitude", type=finite_float, default=12.0, help="flight height, m (default 12)")
    p.add_argument("--yaw-rate-max", type=finite_float, default=30.0, help="max yaw rate, deg/s (default 30)")
    add_site_options(p, default=DEFAULT_SITE)


def _site(args) -> Site:
    """--origin / --heading: where the building stands; the EKF origin (home) is its floor corner."""
    return site_from_args(args.origin, args.heading, DEFAULT_SITE)


def _mission(args, waveform: Waveform | None = None):
    """The rectangle, or with --coverage (fly: --mission coverage) the coverage planner's loop."""
    coverage = getattr(args, "coverage", None)
    fill_gaps = getattr(args, "fill_gaps", None)
    if getattr(args, "mission", None) == "fill-gaps" or (args.command == "plan" and fill_gaps is not None):
        return _fill_gaps_mission(args, waveform)
    if fill_gaps is not None:
        raise UserError("--fill-gaps plans a gap re-flight: add --mission fill-gaps")
    if getattr(args, "mission", None) == "coverage" or (args.command == "plan" and coverage is not None):
        return _coverage_mission(args, waveform)
    if coverage is not None:
        raise UserError("--coverage plans a coverage mission: add --mission coverage")
    if getattr(args, "surface", None) or getattr(args, "all_phases", False) or getattr(args, "bare_walls", False):
        raise UserError("--surface, --all-phases and --bare-walls shape a coverage plan: add --coverage PCT"
                        + (" and --mission coverage" if args.command == "fly" else ""))
    if args.p_traj is None:
        raise UserError("the rectangle mission needs --p-traj PCT (or plan one with --mission coverage --coverage PCT)")
    return Mission(storage=Storage.parse(args.storage), p_traj=args.p_traj / 100.0, turn=args.turn,
                   speed_m_s=args.speed, altitude_m=args.altitude,
                   yaw_rate_max_rad_s=math.radians(args.yaw_rate_max))


PROGRESS_EVERY_S = 10.0
"""A long plan (on an earlier survey's surface, for every servo start position: minutes) says how far it got this
often."""


def planning_progress(every_s: float = PROGRESS_EVERY_S, clock=time.monotonic):
    """progress(loops evaluated, best predicted coverage) for `plan_coverage`: an INFO line every every_s seconds
    (-q silences it), nothing for a plan that is over sooner."""
    start = clock()
    next_at = start + every_s

    def say(n: int, best_pct: float) -> None:
        nonlocal next_at
        now = clock()
        if now >= next_at:
            next_at = now + every_s
            log.info("coverage plan: %d loops evaluated in %.0f s, the best predicts %.2f %% so far", n, now - start,
                     best_pct)
    return say


def _coverage_mission(args, waveform: Waveform | None):
    from sitl.missions.coverage import CoverageTarget, WallBand, mission_time_s, plan_coverage
    from sitl.missions.range_check import planning_limit
    from sitl.missions.surveyed_surface import load_height_field
    if args.coverage is None:
        raise UserError("--mission coverage needs --coverage PCT (the predicted floor coverage to reach)")
    wf = waveform or named_waveform(args.waveform, args.servo_rate, 0)
    spec = args.rangefinder.spec
    try:
        storage = Storage.parse(args.storage)
        surface = load_height_field(args.surface, storage) if args.surface else None
        also = tuple(w for k in range(2 * N_PHASES)
                     if (w := named_waveform(args.waveform, args.servo_rate, k)) != wf) if args.all_phases else ()
        target = CoverageTarget(args.coverage, wf, planning_limit(spec, args.sensor_noise), spec.rate_hz,
                                seen_radius_m=args.seen_radius, also_waveforms=also, surface=surface,
                                walls=None if args.bare_walls else WallBand.of(spec))
        planned = plan_coverage(storage, target, altitude_m=args.altitude,
                                yaw_rate_max_rad_s=math.radians(args.yaw_rate_max), progress=planning_progress())
    except ValueError as exc:
        raise UserError(f"coverage plan: {exc}") from None
    if not args.quiet:
        p = planned.plan
        print(f"coverage plan: predicted R_a {planned.coverage.predicted_ra_pct:.2f} %"
              + (f" (worst of {1 + len(also)} servo start positions)" if also else "")
              + (" on the surface of " + str(args.surface) if surface is not None else "") + ", offsets "
              + ", ".join(f"{w.split()[0]} {o:.1f} m" for w, o in zip(WALLS, p.offsets_m, strict=True))
              + f", corner cut {p.corner_cut_m:g} m, {p.speed_m_s:g} m/s, {planned.mission.path_length_m():.0f} m, "
              f"about {mission_time_s(planned.mission, target.energy) / 60:.1f} min, predicted energy "
              f"{planned.energy_j / 1000:.1f} kJ ({planned.n_evaluated} plans evaluated)")
    return planned.mission


def _fill_gaps_mission(args, waveform: Waveform | None):
    from sitl.missions.coverage import CoverageTarget, mission_time_s
    from sitl.missions.gaps import load_gaps, plan_fill_gaps
    from sitl.missions.range_check import planning_limit
    if args.fill_gaps is None:
        raise UserError("--mission fill-gaps needs --fill-gaps REPORT_DIR (the report whose unseen floor to re-fly)")
    if args.coverage is not None or args.surface or args.all_phases or args.bare_walls:
        raise UserError("--fill-gaps plans on its report's own surface for its own target (--gap-coverage): "
                        "--coverage, --surface, --all-phases and --bare-walls are not used with it")
    wf = waveform or named_waveform(args.waveform, args.servo_rate, 0)
    spec = args.rangefinder.spec
    try:
        storage = Storage.parse(args.storage)
        gaps = load_gaps(args.fill_gaps, storage, _site(args), args.seen_radius)
        target = CoverageTarget(args.gap_coverage, wf, planning_limit(spec, args.sensor_noise), spec.rate_hz,
                                seen_radius_m=args.seen_radius)
        planned = plan_fill_gaps(storage, gaps, target, altitude_m=args.altitude,
                                 yaw_rate_max_rad_s=math.radians(args.yaw_rate_max))
    except ValueError as exc:
        raise UserError(f"fill-gaps plan: {exc}") from None
    if not args.quiet:
        m, rec = planned.mission, planned.mission.plan
        minutes = mission_time_s(m, target.energy) / 60
        bridged = (f", {rec['bridged_cells']} of them inside the report's hull but with no point within "
                   f"{rec['seen_radius_m']:g} m" if rec["bridged_cells"] else "")
        print(f"fill-gaps plan: {rec['gap_cells']} unseen cells ({rec['gap_area_m2']:.1f} m²{bridged}) in "
              f"{planned.n_regions} region(s) of {args.fill_gaps}; predicted to cover {planned.coverage.gap_pct:.1f} "
              f"% of them (merged R_a {planned.coverage.merged_ra_pct:.2f} %), {m.path_length_m():.0f} m at "
              f"{m.speed_m_s:g} m/s, about "
              f"{minutes:.1f} min, predicted energy {planned.energy_j / 1000:.1f} kJ ({planned.n_evaluated} missions "
              "evaluated)")
    return planned.mission


def _default_payload(plant: str) -> str:
    """The firmware in the loop needs an autopilot to talk to; the ideal plant has none."""
    return "firmware" if plant == "jsbsim" else "batch"


def _fly(args) -> int:
    mission = _mission(args, named_waveform(args.waveform, args.servo_rate, args.phase)
                       if args.mission in ("coverage", "fill-gaps") else None)
    cfg = FlyConfig(mission=mission, stockpile=args.stockpile, waveform=args.waveform,
                    servo_peak_rate_rad_s=args.servo_rate, initial_position=args.phase, plant=args.plant,
                    payload=args.payload or _default_payload(args.plant), latency_ms=tuple(args.latency_ms),
                    payload_kg=args.payload_mass, seed=args.seed, rangefinder=args.rangefinder,
                    sensor_noise=args.sensor_noise, pose_error=args.pose_error,
                    faults=FaultSpec.parse(args.fault, seed=args.seed) if args.fault else None, site=_site(args))
    res = fly(cfg, args.out, force=args.force)  # progress: this module's logger (-v/-q)
    if not args.quiet:
        print(f"run written to {res.out_dir} ({res.n_samples} samples, {res.duration_s:.0f} s flight, "
              f"{res.wall_time_s:.2f} s wall)")
    return 0


def _plan(args) -> int:
    mission = _mission(args)
    drift = drift_warning(mission, args.pose_error)
    if drift:
        log.warning(drift)
    out = Path(args.out)
    if not args.out.strip() or out.is_dir():
        raise UserError(f"--out must be a plan file path, not empty or a directory (got {args.out!r})")
    if out.exists() and not args.force:
        raise UserError(f"{out} already exists; choose another --out or pass --force")
    tmp = out.with_name(f".{out.name}.partial-{os.getpid()}")  # beside it: the rename stays on one file system
    try:
        site = _site(args)
        write_qgc_wpl(tmp, mission, site.frame_about(), site.corner.as_tuple())
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise RunFailure(f"cannot write {out}: {exc.strerror or exc}") from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    path = publish_file(tmp, out, force=args.force)
    if not args.quiet:
        print(f"plan written to {path} (load it with MAVProxy 'wp load', QGroundControl or Mission Planner)")
    return 0


def _signing(args):
    from firmware_py.core.keys import load_key
    from firmware_py.hal.signing import SigningConfig
    if args.signing_key is None:
        if args.allow_unsigned:
            raise UserError("--allow-unsigned needs --signing-key")
        return None
    with reading_input():
        key = load_key(args.signing_key)
    return SigningConfig(key, allow_unsigned=args.allow_unsigned)


def _serve(args) -> int:
    signing = _signing(args)  # a bad key file fails before anything starts
    from sitl.runners.serve import ServeOptions, serve, tlog_limits
    return serve(ServeOptions(mission=_mission(args), url=args.mavlink, speedup=args.speedup,
                              duration_s=args.duration, vehicle=args.vehicle, out=Path(args.out), force=args.force,
                              devices_url=args.devices, stockpile=args.stockpile, signing=signing,
                              signing_key_file=args.signing_key,
                              faults=FaultSpec.parse(args.fault, seed=args.seed), rangefinder=args.rangefinder,
                              limits=tlog_limits(args.tlog_max_mb), site=_site(args), sensor_noise=args.sensor_noise,
                              pose_error=args.pose_error))


def _dispatch(args) -> int:
    return {"fly": _fly, "serve": _serve, "plan": _plan}[args.command](args)


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli(build_parser(), argv, _dispatch, config=CONFIG_OPTIONS)


if __name__ == "__main__":
    raise SystemExit(main())
