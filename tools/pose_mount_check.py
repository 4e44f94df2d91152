"""Do the mount self-calibration and the pose correction fight? Pile 1 at P_traj 20 % with a servo 3 deg off,
5 % over-scaled and a LiDAR tilted 2 deg (the calibration campaign's "all three"), flown with each pose-error
profile (seed 0), reported with and without the pose correction: Ve and what the self-calibration found.

    python -m tools.pose_mount_check [--keep DIR]
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

from firmware_py.core.cli import ArgumentParser
from ground.report import ReportOptions, make_report
from sitl.faults.injector import FaultSpec
from sitl.missions.rectangle import Mission
from sitl.runners.fly import FlyConfig, fly

MOUNT_FAULTS = {"servo_offset_deg": 3.0, "servo_scale_pct": 5.0, "boresight_deg": 2.0}
PARAMS = ("servo_offset_deg", "servo_scale", "boresight_tilt_deg", "sweep_yaw_deg")


def main(argv: list[str] | None = None) -> int:
    ap = ArgumentParser(prog="python -m tools.pose_mount_check", description=__doc__)
    ap.add_argument("--keep", type=Path, default=None, help="keep the runs and reports in this folder")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        work = args.keep or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        for profile in ("none", "vio", "flow"):
            run = work / f"mount-faults-{profile}"
            if not (run / "samples.pslog").is_file():
                cfg = FlyConfig(mission=Mission(p_traj=0.2), stockpile="1", payload="firmware", seed=0,
                                pose_error=profile, faults=FaultSpec(**MOUNT_FAULTS))
                fly(cfg, run, force=True, progress=lambda _m: None)
            for corrected in (False, True):
                rep = make_report(run, work / f"report-{profile}-{corrected}",
                                  ReportOptions(plots=False, pose_correction=corrected), force=True)
                cal = rep["self_calibration"] or {}
                print(json.dumps({"pose_error": profile, "pose_correction": corrected,
                                  "ve_pct": round(rep["volume_error_pct"], 2),
                                  "mount": {k: (round(cal[k]["estimate"], 3), cal[k]["applied"]) for k in PARAMS
                                            if k in cal},
                                  "pose_applied": (rep.get("pose_correction") or {}).get("applied"),
                                  "pose_reason": (rep.get("pose_correction") or {}).get("reason")}), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
