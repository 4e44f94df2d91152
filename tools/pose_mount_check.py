"""Do the mount self-calibration and the pose correction fight? (issue 15, item 3)

Each flight is flown twice with the same drift (the same seed): once with a square mount, once with the servo 3 deg
off, 5 % over-scaled and the LiDAR tilted 2 deg (the calibration campaign's "all three"; `--fault` flies others, one
at a time or together, and `--sensor-noise` a noisy sensor on both). Both are reported as a user
reports them (the self-calibration and the pose correction on), the faulted one also without the pose correction.
What the self-calibration found and whether the pose correction was applied are in the table, and the faulted
flight's Ve against its square twin's says whether the two corrections together undo the mount fault under a drift.
The faulted flight is also reported with the mount it flew given (`--mount`, in place of the self-calibration): what
is left then against the square twin is not the calibration's (a faulted servo or LiDAR puts its beams elsewhere, and
the pose correction's own residual differs on the other sampling), and |Ve as found - Ve with the true mount| is the
self-calibration's share.

    python -m tools.pose_mount_check --seeds 0 1 2 --piles 1 2 --keep runs/pose-mount --write docs/pose_error.md
    python -m tools.pose_mount_check --fault sweep_yaw_deg=2 --seeds 3 4 5 --profiles vio flow --keep runs/pm
"""

from __future__ import annotations

import json
import math
import statistics
import tempfile
from pathlib import Path
from typing import NamedTuple

from firmware_py.core.cli import ArgumentParser
from firmware_py.core.sensor_noise import SensorNoiseModel
from ground.report import ReportOptions, make_report
from ground.self_calibration import KnownMount
from sitl.faults.injector import FaultSpec
from sitl.missions.rectangle import Mission
from sitl.runners.fly import FlyConfig, fly
from tools.doc_sections import write_section
from tools.pose_correction_campaign import signed_error_pct

MOUNT_FAULTS = {"servo_offset_deg": 3.0, "servo_scale_pct": 5.0, "boresight_deg": 2.0}
"""The faults flown unless `--fault` names others: the calibration campaign's "all three"."""


class MountFault(NamedTuple):
    """A mount fault `--fault` can fly, by `FaultSpec`'s field: the self-calibration's parameter that finds it
    (report.json's key) and its unit there ("%": a fraction, shown in percent), its short name and its words in the
    table."""

    found: str
    unit: str
    short: str
    words: str


FAULTS = {
    "servo_offset_deg": MountFault("servo_offset_deg", "deg", "offset", "the servo {:g} deg off"),
    "servo_scale_pct": MountFault("servo_scale", "%", "scale", "the servo {:g} % over-scaled"),
    "boresight_deg": MountFault("boresight_tilt_deg", "deg", "tilt", "the LiDAR tilted {:g} deg"),
    "sweep_yaw_deg": MountFault("sweep_yaw_deg", "deg", "sweep yaw", "the sweep yawed {:g} deg"),
}
"""The four mount faults, in the order the table names them."""

PROFILES = ("none", "vio", "flow")
SECTION = "pose-mount-table"
TOLERANCE_PP = 0.3
"""A faulted flight counts as undone when its Ve is within this of its square twin's (issue 15's tolerance)."""


def run_name(faulted: bool, faults: dict[str, float], noise: SensorNoiseModel, profile: str, pile: str,
             p_traj_pct: int, seed: int) -> str:
    """The run folder's name: what was flown (the default faults and no noise keep the names they always had, so a
    kept folder is reused)."""
    kind = "square"
    if faulted:
        named = "-".join(f"{k}{v:g}" for k, v in sorted(faults.items()))
        kind = "mount" if faults == MOUNT_FAULTS else f"mount-{named}"
    if noise is not SensorNoiseModel.NONE:
        kind += f"-{noise.value}"
    return f"{kind}-{profile}-{pile}-{p_traj_pct}-{seed}"


def flight(work: Path, pile: str, p_traj_pct: int, profile: str, seed: int, faulted: bool,
           faults: dict[str, float] = MOUNT_FAULTS, noise: SensorNoiseModel = SensorNoiseModel.NONE) -> Path:
    """The flight's run folder, flown unless it is already there (`--keep` reuses it)."""
    run = work / run_name(faulted, faults, noise, profile, pile, p_traj_pct, seed)
    if not (run / "samples.pslog").is_file():
        cfg = FlyConfig(mission=Mission(p_traj=p_traj_pct / 100.0), stockpile=pile, payload="firmware", seed=seed,
                        pose_error=profile, faults=FaultSpec(**faults) if faulted else None, sensor_noise=noise)
        fly(cfg, run, force=True, progress=lambda _m: None)
    return run


def report(run: Path, pose_correction: bool, mount: KnownMount | None = None) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        return make_report(run, Path(tmp) / "rep",
                           ReportOptions(plots=False, pose_correction=pose_correction, mount=mount), force=True)


def true_mount(faults: dict[str, float]) -> KnownMount:
    """The mount the faults flew (`FaultSpec`'s fields), as `--mount` takes it: what a perfect self-calibration
    would apply."""
    return KnownMount(math.radians(faults.get("servo_offset_deg", 0.0)), faults.get("servo_scale_pct", 0.0) / 100.0,
                      math.radians(faults.get("boresight_deg", 0.0)), math.radians(faults.get("sweep_yaw_deg", 0.0)))


def row(work: Path, pile: str, p_traj_pct: int, profile: str, seed: int, faults: dict[str, float] = MOUNT_FAULTS,
        noise: SensorNoiseModel = SensorNoiseModel.NONE) -> dict:
    square = report(flight(work, pile, p_traj_pct, profile, seed, False, faults, noise), True)
    run = flight(work, pile, p_traj_pct, profile, seed, True, faults, noise)
    off, on, given = report(run, False), report(run, True), report(run, True, true_mount(faults))
    cal = on.get("self_calibration") or {}
    found = {f.found: (cal[f.found]["estimate"], bool(cal[f.found]["applied"])) for f in FAULTS.values()
             if f.found in cal}
    return {"pile": pile, "p_traj": p_traj_pct, "profile": profile, "seed": seed,
            "ve_square": signed_error_pct(square), "ve_pose_off": signed_error_pct(off),
            "ve": signed_error_pct(on), "ve_true_mount": signed_error_pct(given), "found": found,
            "pose_applied": bool((on.get("pose_correction") or {}).get("applied")),
            "in_interval": on.get("truth_in_interval")}


def _found(found: dict) -> str:
    def one(f: MountFault) -> str:
        if f.found not in found:
            return "-"
        v, applied = found[f.found]
        text = f"{v * 100:+.2f} %" if f.unit == "%" else f"{v:+.2f} {f.unit}"
        return text if applied else f"({text})"
    return " / ".join(one(f) for f in FAULTS.values())


def _held(r: dict) -> str:
    """Whether the faulted flight's 90 % volume interval holds the true volume ("-": the report gave none)."""
    held = r.get("in_interval")
    return "-" if held is None else ("yes" if held else "no")


def faults_words(faults: dict[str, float]) -> str:
    """The faults in words ("the servo 3 deg off, the servo 5 % over-scaled and ..."), in `FAULTS`' order."""
    words = [f.words.format(faults[k]) for k, f in FAULTS.items() if k in faults]
    return words[0] if len(words) == 1 else ", ".join(words[:-1]) + " and " + words[-1]


def table(rows: list[dict], command: str, faults: dict[str, float] = MOUNT_FAULTS,
          noise: SensorNoiseModel = SensorNoiseModel.NONE) -> str:
    noisy = "no sensor noise" if noise is SensorNoiseModel.NONE else f"sensor noise `{noise.value}`"
    lines = [
        f"The paper's building (60 x 40 x 15 m, 12 m, 1 m/s), payload firmware in the loop, {noisy}. Each flight "
        f"flown with a square mount and with {faults_words(faults)}, the same drift (the seed); signed Ve (eq. 8) "
        "from `pilescan-ground report` (the self-calibration and the pose correction on; \"pose off\": "
        "`--no-pose-correction`; \"true mount\": the faulted flight reported with the mount it flew given, "
        "`--mount`, in place of the self-calibration: what a perfect self-calibration would leave). Found: the "
        "self-calibration's servo offset / scale / tilt / sweep yaw, in brackets when not applied. Regenerated by `"
        + command + "`.",
        "",
        "| pile | P_traj | profile | seed | Ve, square mount (%) | Ve, faulted, pose off (%) | Ve, faulted (%) | "
        "Ve, faulted, true mount (%) | found | pose corrected | within " + f"{TOLERANCE_PP:g} pp of the square mount | "
        "90 % interval holds the truth |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        near = abs(r["ve"] - r["ve_square"]) <= TOLERANCE_PP
        lines.append(f"| {r['pile']} | {r['p_traj']} % | {r['profile']} | {r['seed']} | {r['ve_square']:+.2f} | "
                     f"{r['ve_pose_off']:+.2f} | {r['ve']:+.2f} | {r['ve_true_mount']:+.2f} | {_found(r['found'])} | "
                     f"{'yes' if r['pose_applied'] else 'no'} | {'yes' if near else 'no'} | {_held(r)} |")
    flown = [f.found for k, f in FAULTS.items() if k in faults]
    names = ", ".join(f.short for k, f in FAULTS.items() if k in faults)
    lines += ["", f"| profile | flights | mount found and applied ({names}) | within "
              f"{TOLERANCE_PP:g} pp | mean \\|Ve - square mount's\\| (pp) | with the true mount: within "
              f"{TOLERANCE_PP:g} pp | mean \\|Ve - square mount's\\| (pp) | the self-calibration's share: mean / max "
              "\\|Ve - true mount's\\| (pp) | intervals holding the truth |",
              "|---|---|---|---|---|---|---|---|---|"]
    for profile in PROFILES:
        rs = [r for r in rows if r["profile"] == profile]
        if not rs:
            continue
        applied = sum(all(r["found"].get(k, (0, False))[1] for k in flown) for r in rs)
        near = sum(abs(r["ve"] - r["ve_square"]) <= TOLERANCE_PP for r in rs)
        gap = statistics.fmean(abs(r["ve"] - r["ve_square"]) for r in rs)
        near_true = sum(abs(r["ve_true_mount"] - r["ve_square"]) <= TOLERANCE_PP for r in rs)
        gap_true = statistics.fmean(abs(r["ve_true_mount"] - r["ve_square"]) for r in rs)
        share = [abs(r["ve"] - r["ve_true_mount"]) for r in rs]
        held = sum(r.get("in_interval") is True for r in rs)
        n = len(rs)
        lines.append(f"| {profile} | {n} | {applied}/{n} | {near}/{n} | {gap:.2f} | {near_true}/{n} | {gap_true:.2f} "
                     f"| {statistics.fmean(share):.2f} / {max(share):.2f} | {held}/{n} |")
    return "\n".join(lines)


def fault(text: str) -> tuple[str, float]:
    """`--fault NAME=VALUE`: a mount fault (`FaultSpec`'s field) and its size."""
    name, sep, value = text.partition("=")
    if not sep or name not in FAULTS:
        raise ValueError(f"expected NAME=VALUE with NAME one of {', '.join(FAULTS)}, got {text!r}")
    try:
        v = float(value)
    except ValueError:
        raise ValueError(f"{name}'s size must be a number, got {value!r}") from None
    if not math.isfinite(v) or v == 0:
        raise ValueError(f"{name}'s size must be a finite number other than 0, got {value!r}")
    return name, v


def main(argv: list[str] | None = None) -> int:
    ap = ArgumentParser(prog="python -m tools.pose_mount_check", description=__doc__)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0], help="drift seeds (default 0)")
    ap.add_argument("--piles", nargs="+", default=["1"], help="the paper's piles (default 1)")
    ap.add_argument("--p-traj", type=int, default=20, help="P_traj [%%] (default 20)")
    ap.add_argument("--profiles", nargs="+", default=list(PROFILES), choices=PROFILES,
                    help="pose-error profiles (default: all three)")
    ap.add_argument("--fault", action="append", default=None, metavar="NAME=VALUE",
                    help="a mount fault to fly (again for more): " + ", ".join(FAULTS)
                    + " (default: " + " ".join(f"{k}={v:g}" for k, v in MOUNT_FAULTS.items()) + ")")
    ap.add_argument("--sensor-noise", type=SensorNoiseModel, default=SensorNoiseModel.NONE,
                    choices=list(SensorNoiseModel), help="the sensors' noise on every flight (default none)")
    ap.add_argument("--keep", type=Path, default=None, help="keep the runs in this folder (and reuse them)")
    ap.add_argument("--write", type=Path, default=None, help="page whose table section to rewrite")
    ap.add_argument("--section", default=SECTION, help=f"the section's name (default {SECTION})")
    args = ap.parse_args(argv)
    if not 0 < args.p_traj < 100:
        ap.error(f"--p-traj must be between 0 and 100, got {args.p_traj}")
    faults = dict(MOUNT_FAULTS)
    if args.fault:
        try:
            faults = dict(fault(f) for f in args.fault)
        except ValueError as e:
            ap.error(f"--fault: {e}")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = args.keep or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        for pile in args.piles:
            for profile in args.profiles:
                for seed in args.seeds[:1] if profile == "none" else args.seeds:  # no drift: every seed flies alike
                    r = row(work, pile, args.p_traj, profile, seed, faults, args.sensor_noise)
                    rows.append(r)
                    print(json.dumps({k: (round(v, 3) if isinstance(v, float) and math.isfinite(v) else v)
                                      for k, v in r.items()}), flush=True)
    command = ("python -m tools.pose_mount_check "
               + "".join(f"--fault {k}={v:g} " for k, v in faults.items() if args.fault)
               + (f"--sensor-noise {args.sensor_noise.value} " if args.sensor_noise is not SensorNoiseModel.NONE
                  else "")
               + "--seeds " + " ".join(map(str, args.seeds)) + " --piles " + " ".join(args.piles)
               + f" --p-traj {args.p_traj}"
               + (" --profiles " + " ".join(args.profiles) if args.profiles != list(PROFILES) else "")
               + (f" --keep {args.keep}" if args.keep else "")
               + (f" --write {args.write}" if args.write else "")
               + (f" --section {args.section}" if args.section != SECTION else ""))
    text = table(rows, command, faults, args.sensor_noise)
    print(text)
    if args.write:
        write_section(args.write, args.section, text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
