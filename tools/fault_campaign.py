"""Fault campaign: every fault class on the same firmware-in-the-loop survey, beside the fault-free run.

    python -m tools.fault_campaign --write docs/reliability.md

For each fault: what the system did (counters), samples flagged, data lost (samples the payload
should have logged and did not), samples wrongly tagged (logged unflagged with a pose that is not
the vehicle's true pose at their time: must be zero), and the volume error next to the fault-free
run's. Targets: within 0.5 pp of fault-free at 10 % packet loss, 1 pp at 30 %; data lost zero
except the unfinished block at a power cut.
"""

from __future__ import annotations

import argparse
import hashlib
import math
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from firmware_py.core.cli import ArgumentParser, UserError, finite_float, run_cli
from firmware_py.core.samplelog import SampleFlags, read_samplelog
from firmware_py.payload import LoopConfig
from ground.report import ReportOptions, summarise, survey_from_samples
from sitl.faults.injector import FaultSpec, wrongly_tagged
from sitl.missions.rectangle import Mission
from sitl.runners.fly import FlyConfig, log_header
from sitl.runners.lockstep_payload import fly_firmware
from sitl.world.stockpile import resolve
from tools.doc_sections import write_section

RECORDS_PER_BLOCK = 500


@dataclass(frozen=True)
class Scenario:
    name: str
    spec: FaultSpec
    what: str
    signed: bool = False  # fly with MAVLink 2 signing on the autopilot <-> payload link
    ends_early: bool = False  # a power cut or a full disk: the log stops there, by design


def survey_duration_s(cfg: FlyConfig) -> float:
    """The survey loop's flight time at the commanded speed (turns at the yaw-rate limit added)."""
    m = cfg.mission
    return m.path_length_m() / m.speed_m_s + 2 * math.pi / m.yaw_rate_max_rad_s


def scenarios(seed: int = 1, cfg: FlyConfig | None = None) -> list[Scenario]:
    """The campaign: each fault class at a setting a real flight can meet (times from survey start)."""
    duration = survey_duration_s(cfg) if cfg is not None else 120.0
    kill_at = round(float(np.random.default_rng(seed).uniform(5.0, max(6.0, duration - 5.0))), 1)
    return [
        Scenario("none", FaultSpec(seed=seed), "fault-free reference"),
        Scenario("loss-10", FaultSpec(seed=seed, link_loss_pct=10), "10 % MAVLink packet loss, both ways"),
        Scenario("loss-30", FaultSpec(seed=seed, link_loss_pct=30), "30 % MAVLink packet loss, both ways"),
        Scenario("dup-reorder", FaultSpec(seed=seed, link_dup_pct=10, link_reorder_pct=10),
                 "10 % duplicated + 10 % reordered packets"),
        Scenario("latency", FaultSpec(seed=seed, link_latency_ms=50, link_jitter_ms=30),
                 "50 ms added latency + 0-30 ms jitter, both ways"),
        Scenario("outage", FaultSpec(seed=seed, link_outage=(20.0, 5.0)), "MAVLink outage of 5 s at 20 s"),
        Scenario("reboot", FaultSpec(seed=seed, autopilot_reboot=(20.0, 3.0)),
                 "autopilot reboot at 20 s: silent 3 s, then time_boot_ms from 0 and default stream rates"),
        Scenario("clock+1h", FaultSpec(seed=seed, clock_jump=(20.0, 3600.0)),
                 "companion wall clock jumps +1 h at 20 s (link signed)", signed=True),
        Scenario("clock-1h", FaultSpec(seed=seed, clock_jump=(20.0, -3600.0)),
                 "companion wall clock jumps -1 h at 20 s (link signed)", signed=True),
        Scenario("nack-5", FaultSpec(seed=seed, i2c_nack_pct=5), "5 % I2C NACKs"),
        Scenario("stuck-busy", FaultSpec(seed=seed, lidar_stuck_busy=(15.0, 2.0)), "LiDAR stuck busy 2 s at 15 s"),
        Scenario("power-glitch", FaultSpec(seed=seed, lidar_power_glitch_at_s=15.0),
                 "LiDAR power glitch (registers reset) at 15 s"),
        Scenario("garbage-2", FaultSpec(seed=seed, lidar_garbage_pct=2), "2 % garbage I2C reads"),
        Scenario("glitch-1", FaultSpec(seed=seed, lidar_glitch_pct=1), "1 % glitch readings (40 m or 1 cm)"),
        Scenario("servo-slow", FaultSpec(seed=seed, servo_slow_factor=0.6),
                 "servo 40 % slower than its calibration"),
        Scenario("servo-delay", FaultSpec(seed=seed, servo_delay_ms=30), "servo answers pulses 30 ms late"),
        Scenario("servo-stuck", FaultSpec(seed=seed, servo_stuck_at_s=30.0), "servo stuck from 30 s"),
        Scenario("power-cut", FaultSpec(seed=seed, power_cut_at_s=40.0), "payload power cut at 40 s",
                 ends_early=True),
        Scenario("kill-random", FaultSpec(seed=seed, power_cut_at_s=kill_at),
                 f"payload killed at a random time (seeded: {kill_at:g} s)", ends_early=True),
        Scenario("disk-full", FaultSpec(seed=seed, disk_full_at_s=40.0), "the log's disk fills up at 40 s",
                 ends_early=True),
    ]


def loop_rate_hz(t_s: np.ndarray) -> tuple[float, float]:
    """(median, lowest) samples per second over the whole 1 s windows of the log: does the loop
    keep its rate whatever the fault? Flagged samples count: the loop ticked."""
    t = np.sort(np.asarray(t_s, dtype=float))
    if len(t) < 2 or t[-1] - t[0] < 2.0:
        return float("nan"), float("nan")
    counts = np.bincount(((t - t[0]) // 1.0).astype(int))[:-1]  # the last window is partial
    return float(np.median(counts)), float(counts.min())


def run_scenario(sc: Scenario, cfg: FlyConfig, tmp: Path) -> dict:
    wf = cfg.servo_waveform()
    header = log_header(cfg, wf)
    t0 = time.perf_counter()
    key = hashlib.sha256(f"pilescan fault campaign {sc.spec.seed}".encode()).digest() if sc.signed else None
    run = fly_firmware(cfg, tmp / f"{sc.name}.pslog", header, faults=sc.spec, seed=sc.spec.seed, signing_key=key)
    log = read_samplelog(tmp / f"{sc.name}.pslog")
    s = log.samples
    storage = cfg.mission.storage
    pile = resolve(cfg.stockpile, storage)
    opts = ReportOptions(plots=False)
    sv = survey_from_samples(s, log.header, storage, cfg.frame, np.array(cfg.lever_arm_body_m), opts)
    rep = summarise(sv, log, opts, pile.volume_m3)
    bad = wrongly_tagged(s, run.true_t_s, run.true_states)
    flagged = {f.name: int(np.count_nonzero(s["flags"] & int(f))) for f in SampleFlags if f}
    ticks = run.loop.ticks
    lost = ticks - len(s)  # readings the loop took that are not in the log
    in_flight = (run.faults or {}).get("pending_at_stop", 0)  # of those, still waiting for a pose at the stop
    f = run.faults or {}
    link = {k: f["link_down"][k] + f["link_up"][k] for k in f.get("link_down", {})}
    signing = f.get("signing") or {}
    refused = sum(st[k] for st in signing.values() for k in ("unsigned", "bad_signature", "replayed"))
    rate_med, rate_min = loop_rate_hz(s["t_s"])
    return {
        "name": sc.name, "what": sc.what, "samples": len(s), "ticks": ticks, "lost": lost, "in_flight": in_flight,
        "ends_early": sc.ends_early, "flagged": flagged, "wrong": int(bad.sum()),
        "volume_m3": rep["volume_m3"], "ve_pct": rep["volume_error_pct"], "ra_pct": rep["coverage_ratio_pct"],
        "warnings": rep["warnings"], "rate_median_hz": rate_med, "rate_min_hz": rate_min,
        "lidar": {k: v for k, v in run.lidar_counters.items() if v and k not in ("ok", "bias")},
        "link": {k: v for k, v in link.items() if v and k not in ("packets",)}, "nacks": f.get("i2c_nacks", 0),
        "glitches": f.get("lidar_glitches", 0), "overruns": run.loop.overruns, "cut": f.get("power_cut", False),
        "disk_full": f.get("disk_full", False), "reboots": f.get("autopilot_reboots", 0),
        "clock_jumps": f.get("clock_jumps", 0), "signed": sc.signed, "signing_refused": refused,
        "timesync_resets": run.pose_status.get("timesync", {}).get("resets", 0),
        "blocks_truncated": log.blocks_truncated, "wall_s": time.perf_counter() - t0,
        "servo_timing": sv.servo_timing if sv.servo_retimed else None,
    }


def _did(r: dict) -> str:
    parts = []
    if r["link"]:
        parts.append("link " + ", ".join(f"{k} {v}" for k, v in r["link"].items()))
    if r["reboots"]:
        parts.append(f"autopilot rebooted {r['reboots']}x")
    if r["clock_jumps"]:
        parts.append(f"companion clock jumped {r['clock_jumps']}x")
    if r["timesync_resets"]:
        parts.append(f"time sync reset {r['timesync_resets']}x and re-converged")
    if r["signed"]:
        parts.append(f"signed frames refused {r['signing_refused']}")
    if r["nacks"]:
        parts.append(f"{r['nacks']} NACKs")
    if r["lidar"]:
        parts.append("LiDAR " + ", ".join(f"{k} {v}" for k, v in r["lidar"].items()))
    if r["glitches"]:
        parts.append(f"{r['glitches']} glitch readings")
    st = r.get("servo_timing")
    if st is not None:
        parts.append(f"ground: servo re-simulated ({st.model}): {st.delay_s * 1e3:.0f} ms late, "
                     f"{st.gain * 100:.0f} % speed; sweeps disagree {st.disagreement_before_m:.2f} -> "
                     f"{st.disagreement_after_m:.2f} m")
    if r["cut"]:
        parts.append("log ends at the last whole block; the report covers the flight up to the cut")
    if r["disk_full"]:
        parts.append(f"payload stopped on '{r['disk_full']}' with every whole block kept")
    if r["overruns"]:
        parts.append(f"{r['overruns']} loop overruns")
    return "; ".join(parts) or "—"


def _warned(r: dict) -> str:
    """The ground report's warnings, shortened to their first clause (the full text is in report.json)."""
    return "; ".join(w.split(":")[0].split(" (")[0] for w in r["warnings"]) or "—"


def table(rows: list[dict]) -> str:
    ref = next(r for r in rows if r["name"] == "none")
    lines = ["| fault | setting | what the system did | ground report warns | samples | loop rate [Hz] median / "
             "lowest 1 s | flagged (stale / no pose / sensor / no return) | data lost | wrongly tagged | R_a [%] "
             "| Ve [%] | Ve − fault-free [pp] |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        fl = r["flagged"]
        lines.append(f"| {r['name']} | {r['what']} | {_did(r)} | {_warned(r)} | {r['samples']:,} | "
                     f"{r['rate_median_hz']:.0f} / {r['rate_min_hz']:.0f} | {fl['STALE_POSE']:,} / "
                     f"{fl['NO_POSE']:,} / {fl['SENSOR_ERROR']:,} / {fl['NO_RETURN']:,} | {r['lost']:,} | "
                     f"{r['wrong']} | {r['ra_pct']:.1f} | {r['ve_pct']:.2f} | {r['ve_pct'] - ref['ve_pct']:+.2f} |")
    return "\n".join(lines)


def checks(rows: list[dict], rate_hz: float) -> list[str]:
    """The issue's targets, each stated with its measured value."""
    ref = rows[0]
    no_wrong = all(r["wrong"] == 0 for r in rows)
    out = [f"- zero wrongly tagged samples in every case: **{'yes' if no_wrong else 'NO'}**"]
    for name, limit in (("loss-10", 0.5), ("loss-30", 1.0)):
        r = next((x for x in rows if x["name"] == name), None)
        if r:
            d = abs(r["ve_pct"] - ref["ve_pct"])
            ok = "yes" if d <= limit else "NO"
            out.append(f"- {name}: Ve within {limit} pp of fault-free: **{ok}** ({d:.2f} pp)")
    lost_ok = all(r["lost"] == 0 or (r["ends_early"] and r["lost"] - r["in_flight"] <= RECORDS_PER_BLOCK)
                  for r in rows)
    early = [r for r in rows if r["ends_early"]]
    detail = "; ".join(f"{r['name']}: {r['lost'] - r['in_flight']} in the unfinished block + {r['in_flight']} "
                       "awaiting their pose" for r in early)
    out.append(f"- data lost: zero, or at most the unfinished {RECORDS_PER_BLOCK}-sample block (plus the readings "
               f"still waiting for their pose, ~{LoopConfig().max_pose_wait_s * 1e3:.0f} ms) when the log ends early: "
               f"**{'yes' if lost_ok else 'NO'}**" + (f" ({detail})" if detail else ""))
    lowest = min(r["rate_min_hz"] for r in rows)
    out.append(f"- the loop keeps its rate: lowest 1 s window {lowest:.0f} Hz over all faults for "
               f"{rate_hz:g} Hz: **{'yes' if lowest >= 0.98 * rate_hz else 'NO'}**")
    return out


def build_parser() -> argparse.ArgumentParser:
    ap = ArgumentParser(prog="python -m tools.fault_campaign", description=__doc__,
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--stockpile", default="1", help="built-in pile number or a mesh/height-field file")
    ap.add_argument("--p-traj", type=finite_float, default=20.0, help="percent (0-50)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--only", default=None, help="comma-separated scenario names (the fault-free one always runs)")
    ap.add_argument("--write", type=Path, default=None, help="write the reliability page here")
    return ap


def main(argv: list[str] | None = None) -> int:
    return run_cli(build_parser(), argv, _body)


def _body(args: argparse.Namespace) -> int:
    if not 0 < args.p_traj < 50:
        raise UserError(f"--p-traj must be a percentage in (0, 50), got {args.p_traj:g}")
    if args.write is not None and (not str(args.write).strip() or not args.write.parent.is_dir()):
        raise UserError(f"--write {str(args.write)!r}: the directory must exist")
    cfg = FlyConfig(mission=Mission(p_traj=args.p_traj / 100), stockpile=args.stockpile, payload="firmware")
    resolve(cfg.stockpile, cfg.mission.storage)  # a bad --stockpile fails now, not after the first flight
    chosen = scenarios(args.seed, cfg)
    if args.only:
        names = {n.strip() for n in args.only.split(",")}
        unknown = names - {sc.name for sc in chosen}
        if unknown:
            raise UserError(f"--only: no scenario {', '.join(sorted(unknown))}; the scenarios are "
                            + ", ".join(sc.name for sc in chosen))
        chosen = [sc for sc in chosen if sc.name in names or sc.name == "none"]
    rows = []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for i, sc in enumerate(chosen, 1):
            print(f"[{i}/{len(chosen)}] {sc.name}: {sc.what} ...", file=sys.stderr, end="", flush=True)
            rows.append(run_scenario(sc, cfg, Path(tmp)))
            print(f" {rows[-1]['wall_s']:.1f} s", file=sys.stderr, flush=True)
    text = table(rows)
    print(text)
    if args.write:
        checks_text = checks(rows, cfg.lidar.rate_hz)
        write_section(args.write, "fault-campaign",
            "## The fault campaign\n\n"
            f"Regenerate with `python -m tools.fault_campaign --write {args.write}` "
            f"({time.perf_counter() - t0:.0f} s). "
            f"Pile {args.stockpile}, P_traj {args.p_traj:g} %, the payload firmware in the loop (lockstep), seed "
            f"{args.seed}; times are from the start of the survey. *Flagged* samples are logged but left out of the "
            "cloud; *data lost* counts readings the loop took that never reached the log; *wrongly tagged* counts "
            "unflagged samples whose pose is more than 10 cm or 1° from the vehicle's true pose at their time; "
            "*ground report warns* is the first clause of each warning the ground station's report gives "
            "(`pilescan-ground report`), and R_a its reconstructed-area ratio (eq. 9), the coverage left.\n\n"
            + "\n".join(checks_text) + "\n\n" + text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
