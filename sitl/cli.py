"""`pilescan-sitl`: fly survey missions in the software-in-the-loop simulator."""

from __future__ import annotations

import math
import sys
from collections.abc import Sequence

from firmware_py.cli_util import ArgumentParser, finite_float, run_cli
from firmware_py.servo_waveform import N_PHASES
from firmware_py.storage import Storage
from sitl.mission import TURN_MODES, Mission
from sitl.run import PLANTS, FlyConfig, fly


def build_parser() -> ArgumentParser:
    ap = ArgumentParser(prog="pilescan-sitl", description=__doc__)
    sub = ap.add_subparsers(dest="command", required=True, parser_class=ArgumentParser)
    f = sub.add_parser("fly", help="fly a survey and write a run directory")
    f.add_argument("--stockpile", required=True, help="1, 2 (the paper's piles) or an STL/OBJ mesh path")
    f.add_argument("--p-traj", type=finite_float, required=True, metavar="PCT",
                   help="waypoint offset from the walls, percent of L and W (eqs. 17-18), 0-50")
    f.add_argument("--storage", default="60x40x15", help="building LxWxH in metres (default 60x40x15)")
    f.add_argument("--turn", choices=TURN_MODES, default="one-step", help="corner turns (Fig. 15)")
    f.add_argument("--speed", type=finite_float, default=1.0, help="flight speed, m/s (default 1.0)")
    f.add_argument("--altitude", type=finite_float, default=12.0, help="flight height, m (default 12)")
    f.add_argument("--yaw-rate-max", type=finite_float, default=30.0, help="max yaw rate, deg/s (default 30)")
    f.add_argument("--waveform", choices=("semi-triangular", "sinusoidal"), default="semi-triangular",
                   help="servo waveform (eq. 1; C=0.95 or C=0)")
    f.add_argument("--servo-rate", type=finite_float, default=5.0,
                   help="peak servo rate, rad/s (sets f; default 5 -> 0.67 Hz semi-triangular)")
    f.add_argument("--phase", type=int, default=0, metavar="K",
                   help=f"servo initial position 0..{2 * N_PHASES - 1} (Fig. 9: {N_PHASES} phases x 2 "
                        f"directions; K >= {N_PHASES} sweeps the other way)")
    f.add_argument("--plant", choices=PLANTS, default="jsbsim",
                   help="vehicle: jsbsim (F450 flight dynamics + autopilot, default) or ideal (kinematic)")
    f.add_argument("--payload-mass", type=finite_float, default=0.040, metavar="KG",
                   help="payload mass, kg (0.040: LIDAR-Lite + servo; 0.370 2D LiDAR; 0.830 3D)")
    f.add_argument("--seed", type=int, default=0, help="seed of the run's random draws")
    f.add_argument("--out", required=True, help="run directory to write")
    f.add_argument("--force", action="store_true", help="overwrite a run already in --out")
    f.add_argument("--quiet", action="store_true", help="print nothing but errors")
    return ap


def _fly(args) -> int:
    mission = Mission(storage=Storage.parse(args.storage), p_traj=args.p_traj / 100.0, turn=args.turn,
                      speed_m_s=args.speed, altitude_m=args.altitude,
                      yaw_rate_max_rad_s=math.radians(args.yaw_rate_max))
    cfg = FlyConfig(mission=mission, stockpile=args.stockpile, waveform=args.waveform,
                    servo_peak_rate_rad_s=args.servo_rate, initial_position=args.phase, plant=args.plant,
                    payload_kg=args.payload_mass, seed=args.seed)
    progress = None if args.quiet else (lambda msg: print(f"pilescan-sitl: {msg}", file=sys.stderr))
    res = fly(cfg, args.out, force=args.force, progress=progress)
    if not args.quiet:
        print(f"run written to {res.out_dir} ({res.n_samples} samples, {res.duration_s:.0f} s flight, "
              f"{res.wall_time_s:.2f} s wall)")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli(build_parser(), argv, _fly)


if __name__ == "__main__":
    raise SystemExit(main())
