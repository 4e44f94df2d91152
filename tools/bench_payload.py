"""Payload benchmarks (medians; never asserted in tests).

1. Payload CPU per sample: the real LIDAR-Lite driver, servo driver and model, pose tagging and
   the sample log (one fsync per 500-record block) on a bus that answers at once, a clock that
   never waits and a pose source that always has a pose: what the payload itself costs per sample,
   without any simulator. (The MAVLink pump is measured separately in the lockstep run.)
2. Whole lockstep mission with the firmware in the loop (`fly --payload firmware`), as a ratio
   to real time. Usage: python -m tools.bench_payload [--repeat 3] [--write docs/benchmarks-payload.md]
   [--readme README.md]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from firmware_py.core.samplelog import SampleLogWriter
from firmware_py.core.waveform import named_waveform
from firmware_py.drivers.lidarlite import PRESET_FAST_500HZ, LidarLite, LidarLiteConfig
from firmware_py.drivers.servo import SweepServo
from firmware_py.hal.clock import SimClock
from firmware_py.payload import LoopConfig, PayloadLoop
from sitl.missions.rectangle import Mission
from sitl.runners.fly import FlyConfig, fly
from tools.doc_sections import write_dated_section


class InstantLidarBus:
    """Register reads answer at once: never busy, 12.34 m; writes are accepted."""

    def write(self, addr, data):
        self._reg = data[0]

    def read(self, addr, n):
        if n == 1:
            return {0x02: bytes([PRESET_FAST_500HZ.sig_count_val]), 0x04: bytes([PRESET_FAST_500HZ.acq_config]),
                    0x1C: bytes([PRESET_FAST_500HZ.threshold_bypass])}.get(self._reg, b"\x00")
        return bytes([1234 >> 8, 1234 & 0xFF])[:n]

    def write_read(self, addr, data, n):
        raise AssertionError("split transfers only")

    def close(self):
        pass


class NullPwm:
    def set_pulse_us(self, pulse_us):
        pass

    def disable(self):
        pass

    def close(self):
        pass


@dataclass(frozen=True)
class _Pose:
    pos_ned_m: tuple = (1.0, 2.0, -12.0)
    roll_rad: float = 0.01
    pitch_rad: float = -0.02
    yaw_rad: float = 1.0
    age_s: float = 0.01
    stale: bool = False
    missing: bool = False


class ReadyPose:
    def pump(self):
        pass

    def pose_at(self, t_ns):
        return _Pose()


def payload_cpu_us(n: int, tmp: Path) -> float:
    clock = SimClock()
    lidar = LidarLite(InstantLidarBus(), clock, LidarLiteConfig(preset=PRESET_FAST_500HZ))
    servo = SweepServo(NullPwm(), named_waveform("semi-triangular"))
    with SampleLogWriter(tmp / "b.pslog", {"bench": True}, overwrite=True) as log:
        loop = PayloadLoop(lidar, servo, ReadyPose(), clock, log, LoopConfig())
        t0 = time.perf_counter()
        for _ in range(n):
            clock.sleep_until_ns(clock.now_ns() + 2_000_000)
            loop.tick()
        return (time.perf_counter() - t0) / n * 1e6


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--p-traj", type=float, default=20.0)
    ap.add_argument("--readme", type=Path,
                    help="also write the table into this page's marked section bench-payload (README.md)")
    ap.add_argument("--write", type=Path)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        cpu = statistics.median(payload_cpu_us(50_000, Path(tmp)) for _ in range(args.repeat))
        cfg = FlyConfig(mission=Mission(p_traj=args.p_traj / 100), payload="firmware")
        walls, sim = [], 0.0
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            res = fly(cfg, Path(tmp) / "run", force=True)
            walls.append(time.perf_counter() - t0)
            sim = res.duration_s + 10.0  # the survey plus the settle/time-sync phase
    wall = statistics.median(walls)
    text = "\n".join([
        f"Medians of {args.repeat} runs.", "",
        "| benchmark | median | target |", "|---|---|---|",
        f"| payload CPU per sample (driver, servo, tagging, log; no simulator) | {cpu:.1f} µs | ≤ 50 µs |",
        f"| lockstep mission, firmware in the loop, P_traj {args.p_traj:g} % ({sim:.0f} s simulated) | {wall:.1f} s "
        f"= {sim / wall:.1f}× real time | ≥ 50× |",
    ])
    print(text)
    if args.write:
        args.write.write_text("# Payload benchmarks\n\nRegenerate with `python -m tools.bench_payload --write "
                              f"{args.write}`.\n\n{text}\n")
    if args.readme:
        write_dated_section(args.readme, "tools.bench_payload", text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
