"""Networked SITL, end to end, as three separate programs talk on a real drone:

1. `pilescan-sitl serve --devices tcp:...`: the autopilot (JSBSim + ours) on MAVLink/UDP, and the
   emulated LIDAR-Lite and servo behind the TCP device bridge, in real time (with `--rangefinder tfmini`
   an emulated TFMini on a pseudo-terminal too, whose path serve prints);
2. `pilescan-payload --mavlink udpout:... --hal sitl:...` (a TFMini: `--rangefinder tfmini --uart
   serial:/dev/pts/N --pwm pwm:tcp:...`): the unchanged payload firmware, its own process;
3. a scripted ground station (pymavlink): upload the plan, arm, AUTO, wait for the landing.

Then the ground station builds the report from the payload's log. With --compare, the same survey is
flown in lockstep (`fly --payload firmware`) and the volumes are set side by side. Real time: the
default survey takes ~3 minutes of wall time.

    python -m tools.fly_networked --stockpile 1 --p-traj 20 --out runs/networked --compare
    python -m tools.fly_networked --pose-error flow --seed 0 --out runs/networked-flow
    python -m tools.fly_networked --rangefinder tfmini --storage 30x20x10 --altitude 9 --p-traj 25 \
        --sensor-noise datasheet --out runs/networked-tfmini --compare
"""

from __future__ import annotations

import argparse
import json
import re
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from firmware_py.core.cli import ExitCode, NoVolumeError
from firmware_py.core.keys import load_key
from firmware_py.core.rundir import PLAN_FILE, SAMPLES_FILE, TRUTH_FILE
from firmware_py.core.samplelog import UNPOSED, read_samplelog
from ground.report import ReportOptions, header_geometry, make_report, read_log_input
from sitl.mavlink.gcs import fly_plan
from sitl.missions.rectangle import Mission
from sitl.runners.fly import FlyConfig, fly
from tools.pose_correction_campaign import clock_offset_s, on_log_clock, trajectory_rms_m


def free_port(kind: int) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


_PTY_LINE = re.compile(r"TFMini on (/dev/[^\s:]+)")


class StderrLines:
    """A child's stderr read line by line in a thread (so its pipe never fills), kept; `pty` is set,
    and `pty_seen` signalled, when serve says where its TFMini streams."""

    def __init__(self, proc: subprocess.Popen) -> None:
        self.lines: list[str] = []
        self.pty: str | None = None
        self.pty_seen = threading.Event()
        self._thread = threading.Thread(target=self._read, args=(proc,), daemon=True)
        self._thread.start()

    def _read(self, proc: subprocess.Popen) -> None:
        for line in proc.stderr:
            self.lines.append(line.rstrip("\n"))
            m = _PTY_LINE.search(line)
            if m and self.pty is None:
                self.pty = m.group(1)
                self.pty_seen.set()

    def text(self) -> str:
        self._thread.join(timeout=2.0)
        return "\n".join(self.lines)


def wait_pty(lines: StderrLines, proc: subprocess.Popen, timeout_s: float) -> str:
    """The TFMini's pseudo-terminal, once serve has printed it."""
    end = time.monotonic() + timeout_s
    while not lines.pty_seen.wait(0.2):
        if proc.poll() is not None:
            raise RuntimeError(f"the SITL exited early ({proc.returncode}): {lines.text()}")
        if time.monotonic() > end:
            raise RuntimeError(f"the SITL did not say where its TFMini streams within {timeout_s:g} s")
    return lines.pty


def wait_tcp(port: int, proc: subprocess.Popen, timeout_s: float, lines: StderrLines | None = None) -> None:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if proc.poll() is not None:
            err = lines.text() if lines is not None else (proc.stderr.read() if proc.stderr else "")
            raise RuntimeError(f"the SITL exited early ({proc.returncode}): {err}")
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return
        except OSError:
            time.sleep(0.1)
    raise RuntimeError(f"the SITL's device bridge did not open port {port} within {timeout_s:g} s")


def _stamp(path: Path) -> tuple[int, int] | None:
    try:
        st = path.stat()
    except OSError:
        return None
    return st.st_ino, st.st_mtime_ns


def wait_logging(log: Path, proc: subprocess.Popen, timeout_s: float, before: tuple[int, int] | None = None) -> None:
    """Until the payload process has logged a posed sample: then it is tagging its samples and the flight may start,
    so its log holds the vehicle on the floor before take-off. A fixed wait raced the process's start-up on a loaded
    machine (its log began after AUTO); its first block holds about a second of samples without a pose while its time
    sync converges, which on a loaded machine could outlast an arming. before: the log's (inode, mtime) before the
    process started, so that an older log at that path does not count."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if proc.poll() is not None:
            raise RuntimeError(f"the payload exited early ({proc.returncode})")
        stamp = _stamp(log)
        if stamp is not None and stamp != before and _posed(read_samplelog(log).samples).any():
            return
        time.sleep(0.2)
    raise RuntimeError(f"the payload logged no posed sample within {timeout_s:g} s")


def _posed(samples: np.ndarray) -> np.ndarray:
    """The samples tagged with a current pose."""
    return (samples["flags"] & int(UNPOSED)) == 0


def _stop(proc: subprocess.Popen, timeout_s: float = 10.0) -> int:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode


@dataclass(frozen=True)
class NetworkedRun:
    out: Path
    report: dict | None  # None: not asked for (report=False), or the flight gave no volume (`no_volume` says why)
    wall_s: float
    payload_exit: int
    no_volume: str | None = None


def fly_networked(mission_args: list[str], storage: str, stockpile: str, out: Path, phase: int = 0,
                  timeout_s: float = 900.0, flight_s: float | None = None, say=print,
                  signing_key: Path | None = None, rangefinder: str = "lidarlite-v3",
                  serve_args: list[str] | None = None, site_args: list[str] | tuple[str, ...] = (),
                  payload_args: list[str] | tuple[str, ...] = (), report: bool = True) -> NetworkedRun:
    """Run the three programs for one survey; the run directory gets samples.pslog and a report (the log as
    logged: without the pose correction, which `main` makes as a second report where the pose drifts).

    With flight_s, stop the payload (SIGTERM) that long after AUTO instead of waiting for the landing.
    With signing_key (a key file), all three sign their MAVLink and the device bridge asks for the key.
    rangefinder "tfmini": serve streams an emulated TFMini on a pseudo-terminal and the payload reads it
    there with pyserial (the servo stays on the device bridge). serve_args go to serve as they are
    (`--sensor-noise datasheet`, `--fault ...`).
    site_args (["--origin", "LAT,LON,ALT", "--heading", "DEG"]) go to the SITL and to the payload alike:
    the served autopilot's EKF origin and the payload's header (and the origin it sends) then agree.
    payload_args go to the payload as they are (`--stream udp:HOST:PORT`); report=False skips the report.
    """
    out.mkdir(parents=True, exist_ok=True)
    keyed = ["--signing-key", str(signing_key)] if signing_key is not None else []
    key = load_key(signing_key) if signing_key is not None else None
    mav_port, dev_port = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_STREAM)
    t0 = time.perf_counter()
    tfmini = rangefinder == "tfmini"
    sitl = subprocess.Popen([sys.executable, "-m", "sitl.cli", "serve", "--mavlink", f"udp:127.0.0.1:{mav_port}",
                             "--devices", f"tcp:127.0.0.1:{dev_port}", "--stockpile", stockpile, "--storage", storage,
                             *mission_args, *site_args, "--out", str(out), "--force", *keyed, "--rangefinder",
                             rangefinder, *(serve_args or [])], stderr=subprocess.PIPE, text=True)
    lines = StderrLines(sitl)
    payload = None
    try:
        wait_tcp(dev_port, sitl, 30.0, lines)
        say(f"SITL up: MAVLink udp:127.0.0.1:{mav_port}, devices tcp:127.0.0.1:{dev_port}")
        if tfmini:
            pty = wait_pty(lines, sitl, 30.0)
            say(f"TFMini streaming on {pty}")
            sensor = ["--rangefinder", "tfmini", "--uart", f"serial:{pty}", "--pwm", f"pwm:tcp:127.0.0.1:{dev_port}:0"]
        else:
            sensor = ["--hal", f"sitl:127.0.0.1:{dev_port}"]
        before = _stamp(out / SAMPLES_FILE)
        payload = subprocess.Popen([sys.executable, "-m", "firmware_py.cli", "--mavlink",
                                    f"udpout:127.0.0.1:{mav_port}", *sensor,
                                    "--out", str(out / SAMPLES_FILE), "--force", "--storage", storage,
                                    "--phase", str(phase), "--stop-on-disarm", "--quiet", *site_args, *keyed,
                                    *payload_args])
        wait_logging(out / SAMPLES_FILE, payload, 120.0, before)  # its time sync and pose streams settle first
        fly_plan(f"udpout:127.0.0.1:{mav_port}", out / PLAN_FILE, timeout_s, say=lambda m: say(f"  {m}"),
                 fly_s=flight_s, signing_key=key)
        if flight_s is None:
            say("landed and disarmed")
            try:
                payload.wait(timeout=15.0)  # --stop-on-disarm
            except subprocess.TimeoutExpired:
                say("payload still running after the disarm: stopping it")
        code = _stop(payload)
    finally:
        if payload is not None:
            _stop(payload)
        _stop(sitl)
    wall = time.perf_counter() - t0
    if not report:
        return NetworkedRun(out, None, wall, code)
    try:
        rep = make_report(out, out / "report", ReportOptions(plots=False, pose_correction=False), force=True)
    except NoVolumeError as exc:  # e.g. a flight of a few seconds: every sweep on one line
        say(f"no report: {exc}")
        return NetworkedRun(out, None, wall, code, no_volume=str(exc))
    return NetworkedRun(out, rep, wall, code)


def trajectory_rms(run: Path, correction: dict, rangefinder: dict | None = None
                   ) -> tuple[float, float, float, float] | None:
    """The networked flight's trajectory RMS before and after the corrections (the pose correction's record and
    the rangefinder height's, as report.json has them; `serve` keeps the truth on the
    simulator's clock: put on the payload log's by the estimated trajectory, `clock_offset_s`), the offset and
    how far apart the two estimates stay there (m); None without a trajectory in truth.json."""
    truth = json.loads((run / TRUTH_FILE).read_text())
    traj = (truth.get("pose_error") or {}).get("trajectory")
    if not traj:
        return None
    inp = read_log_input(run)
    _, frame, _ = header_geometry(inp.log, inp.log_path)
    s = inp.log.samples
    logged_w = frame.ned_to_w(np.column_stack([s["x_m"], s["y_m"], s["z_m"]]).astype(float))
    ok = np.isfinite(logged_w).all(axis=1) & np.isfinite(s["t_s"])
    offset_s, fit_m = clock_offset_s(traj, s["t_s"][ok], logged_w[ok])
    before, after = trajectory_rms_m(on_log_clock(truth, offset_s), correction, rangefinder)
    return before, after, offset_s, fit_m


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--stockpile", default="1")
    ap.add_argument("--p-traj", type=float, default=20.0, help="percent")
    ap.add_argument("--storage", default="60x40x15")
    ap.add_argument("--altitude", type=float, default=12.0)
    ap.add_argument("--speed", type=float, default=1.0, help="m/s")
    ap.add_argument("--phase", type=int, default=0)
    ap.add_argument("--out", type=Path, default=Path("runs/networked"))
    ap.add_argument("--compare", action="store_true", help="also fly the lockstep SITL and compare volumes")
    ap.add_argument("--json", type=Path, help="write the figures here")
    ap.add_argument("--signing-key", type=Path, default=None, metavar="FILE",
                    help="sign MAVLink on every link and authenticate the device bridge with this key file")
    ap.add_argument("--rangefinder", choices=("lidarlite-v3", "tfmini"), default="lidarlite-v3",
                    help="tfmini: the payload reads an emulated TFMini over a pseudo-terminal with pyserial")
    ap.add_argument("--sensor-noise", choices=("none", "datasheet", "appendix-a"), default="none",
                    help="the simulated sensor noise (serve's --sensor-noise; both flights)")
    ap.add_argument("--pose-error", choices=("none", "flow", "vio"), default="none",
                    help="the autopilot's indoor pose estimate (serve's --pose-error; both flights); the report is "
                         "then made twice, without and with --pose-correction")
    ap.add_argument("--seed", type=int, default=0, help="seed of the noise and pose-error draws (both flights)")
    ap.add_argument("--origin", default=None, metavar="LAT,LON,ALT",
                    help="the site's floor corner (serve and payload --origin; default: the SITL's)")
    ap.add_argument("--heading", default=None, metavar="DEG", help="the building's heading (serve and payload)")
    args = ap.parse_args(argv)
    site_args = ([f"--origin={args.origin}"] if args.origin is not None else []) + (
        [f"--heading={args.heading}"] if args.heading is not None else [])
    mission_args = ["--p-traj", f"{args.p_traj:g}", "--altitude", f"{args.altitude:g}", "--speed", f"{args.speed:g}"]
    try:
        net = fly_networked(mission_args, args.storage, args.stockpile, args.out / "networked", args.phase,
                            signing_key=args.signing_key, rangefinder=args.rangefinder, site_args=site_args,
                            serve_args=["--sensor-noise", args.sensor_noise, "--pose-error", args.pose_error,
                                        "--seed", str(args.seed)])
    except RuntimeError as exc:  # a process refused the flight or did not come up: its own words, one line
        print(f"fly_networked: {exc}", file=sys.stderr)
        return int(ExitCode.RUNTIME)
    if net.report is None:
        print(f"networked: {net.no_volume}", file=sys.stderr)
        return int(ExitCode.NO_VOLUME)
    v_net = net.report["volume_m3"]
    print(f"networked: {v_net:,.1f} m^3, Ve {net.report['volume_error_pct']:.3f} %, "
          f"{net.report['n_samples']:,} samples, {net.wall_s:.0f} s wall, payload exit {net.payload_exit}")
    figures = {"networked_volume_m3": v_net, "networked_ve_pct": net.report["volume_error_pct"],
               "networked_samples": net.report["n_samples"], "networked_wall_s": net.wall_s,
               "true_volume_m3": net.report["true_volume_m3"]}
    if args.pose_error != "none":
        fixed = make_report(args.out / "networked", args.out / "networked" / "report-pose-corrected",
                            ReportOptions(plots=False, pose_correction=True), force=True)
        pc = fixed.get("pose_correction") or {}
        print(f"networked, --pose-correction: {fixed['volume_m3']:,.1f} m^3, Ve {fixed['volume_error_pct']:.3f} % "
              f"(correction {'applied' if pc.get('applied') else 'not applied'})")
        figures.update(networked_corrected_volume_m3=fixed["volume_m3"],
                       networked_corrected_ve_pct=fixed["volume_error_pct"], pose_correction=pc)
        try:
            rms = trajectory_rms(args.out / "networked", pc, fixed.get("rangefinder_height"))
        except ValueError as exc:  # a truth.json and a log that are not one flight: say so, keep the volumes
            print(f"networked trajectory RMS not measured: {exc}", file=sys.stderr)
            rms = None
        if rms is not None:
            before, after, offset_s, fit_m = rms
            print(f"networked trajectory RMS against the truth: {before:.3f} m logged, {after:.3f} m corrected "
                  f"(truth put on the log's clock: offset {offset_s:.3f} s, estimates {fit_m * 100:.1f} cm apart)")
            figures.update(networked_trajectory_rms_before_m=before, networked_trajectory_rms_after_m=after)
    if args.compare:
        from firmware_py.core.sensor import Rangefinder
        from firmware_py.core.storage import Storage
        from sitl.sensing.pose_drift import PoseErrorProfile
        cfg = FlyConfig(mission=Mission(storage=Storage.parse(args.storage), p_traj=args.p_traj / 100,
                                        altitude_m=args.altitude, speed_m_s=args.speed),
                        stockpile=args.stockpile, payload="firmware", initial_position=args.phase,
                        rangefinder=Rangefinder.named(args.rangefinder), sensor_noise=args.sensor_noise,
                        pose_error=PoseErrorProfile(args.pose_error), seed=args.seed)
        if site_args:
            from firmware_py.core.site import DEFAULT_SITE, parse_heading_deg, parse_origin, site_from_args
            cfg = replace(cfg, site=site_from_args(parse_origin(args.origin) if args.origin else None,
                                                   parse_heading_deg(args.heading) if args.heading else None,
                                                   DEFAULT_SITE))
        fly(cfg, args.out / "lockstep", force=True)
        lock = make_report(args.out / "lockstep", args.out / "lockstep" / "report",
                           ReportOptions(plots=False, pose_correction=False), force=True)
        diff = 100.0 * (v_net - lock["volume_m3"]) / lock["volume_m3"]
        print(f"lockstep:  {lock['volume_m3']:,.1f} m^3, Ve {lock['volume_error_pct']:.3f} %, "
              f"{lock['n_samples']:,} samples")
        print(f"networked vs lockstep volume: {diff:+.3f} % (target within 0.5 %)")
        figures.update(lockstep_volume_m3=lock["volume_m3"], lockstep_ve_pct=lock["volume_error_pct"],
                       networked_vs_lockstep_pct=diff)
    if args.json:
        args.json.write_text(json.dumps(figures, indent=2) + "\n")
    return 0 if net.payload_exit == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
