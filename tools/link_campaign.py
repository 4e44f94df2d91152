"""Link campaign: bounded loopback floods against `pilescan-sitl serve` while a ground station works.

For each flood a fresh `serve` (kinematic vehicle, its own folder) listens on a free loopback port;
a pymavlink ground station connects, then, while another process floods the same port from 1 or
10 source ports at a bounded rate for a bounded time, the ground station reads a parameter every
second and uploads a mission. Measured per flood, from the ground station's side unless said:

- ATTITUDE/s it received; reply latency (PARAM_REQUEST_READ -> PARAM_VALUE, and each mission
  request answered) median and max, and replies lost; the mission upload time;
- tlog growth during the flood (the server's telemetry.tlog), and the server's resident memory
  (VmRSS from /proc, peak of the samples);
- unsolicited messages: what reached the ground station that is neither telemetry nor an answer
  to one of its own requests (a reply addressed to another sender, a STATUSTEXT about another
  sender's request, a PARAM_VALUE it did not ask for).

Targets (issue 12): ATTITUDE >= 45/s, every reply within 0.5 s, tlog growth bounded, no
unsolicited message. Usage (a full run takes about 3 minutes)::

    python -m tools.link_campaign                          # print the table
    python -m tools.link_campaign --write docs/reliability.md
    python -m tools.link_campaign --only truncated         # some floods only
    python -m tools.link_campaign --server-path /old/checkout   # measure another version of serve

Last, MAVProxy (when installed) connects to a fresh serve: the seconds from "online system 1" to
"Received N parameters", and whether it printed "fence breach".

`--write` replaces the section between `<!-- link-campaign:start -->` and `<!-- link-campaign:end -->`
(appended at the end of the file when absent).
"""

from __future__ import annotations

import argparse
import math
import multiprocessing as mp
import os
import queue
import random
import re
import shutil
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from tools.doc_sections import markers, write_section

ROOT = Path(__file__).resolve().parents[1]
SECTION = "link-campaign"
START, END = markers(SECTION)
GCS_SYS, GCS_COMP = 255, 190
FLOOD_SYS0 = 100  # flood sender i uses system id FLOOD_SYS0 + i
TELEMETRY = frozenset({"HEARTBEAT", "SYS_STATUS", "SYSTEM_TIME", "ATTITUDE", "LOCAL_POSITION_NED",
                       "GLOBAL_POSITION_INT", "VFR_HUD", "MISSION_CURRENT", "HOME_POSITION"})
TARGET_ATTITUDE_HZ = 45.0
TARGET_REPLY_S = 0.5
REPLY_LOST_S = 3.0
"""A reply not back within this long is counted lost (and its latency as this long)."""


# ----- floods ----------------------------------------------------------------------------------------

def _frame(msg, sysid: int, seq: int) -> bytes:
    mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=1)
    mav.seq = seq % 256
    return bytes(msg.pack(mav))


def flood_datagram(kind: str, sender: int, k: int, rng: random.Random) -> bytes:
    """The k-th datagram of a flood of `kind` from sender index `sender`."""
    sysid = FLOOD_SYS0 + sender
    if kind == "random":
        return rng.randbytes(rng.randint(1, 280))
    if kind == "truncated":  # a v2 header claiming a 255-byte payload, and nothing else
        return bytes([mavlink.PROTOCOL_MARKER_V2, 255, 0, 0, k % 256, sysid, 1, 0, 0, 0])
    if kind == "bad_crc":
        frame = bytearray(_frame(mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3), sysid, k))
        frame[-1] ^= 0xFF
        return bytes(frame)
    if kind == "command":  # absurd COMMAND_LONGs: unknown ids, known ones with NaN / inf / huge params
        command = rng.choice([rng.randint(0, 65535), mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_CMD_NAV_TAKEOFF,
                              mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_CMD_REQUEST_MESSAGE])
        params = [rng.choice([math.nan, math.inf, -math.inf, 3.4e38, -1.0, 1e9]) for _ in range(7)]
        return _frame(mavlink.MAVLink_command_long_message(1, 1, command, 0, *params), sysid, k)
    if kind == "param_nan":
        name = rng.choice([b"PS_SPEED_MS", b"PS_ALT_M", b"NO_SUCH_PARAM"])
        return _frame(mavlink.MAVLink_param_set_message(1, 1, name, math.nan, mavlink.MAV_PARAM_TYPE_REAL32),
                      sysid, k)
    if kind == "mission_count":
        return _frame(mavlink.MAVLink_mission_count_message(1, 1, 65535, 0), sysid, k)
    raise ValueError(f"unknown flood {kind!r}")


FLOOD_KINDS = ("random", "truncated", "bad_crc", "command", "param_nan", "mission_count")


def flood(port: int, kind: str, senders: int, rate_hz: float, duration_s: float, seed: int = 0) -> int:
    """Send `kind` datagrams to 127.0.0.1:port from `senders` source ports, rate_hz in all, for duration_s.

    Bounded in rate and time; returns the number sent. Replies to the flooders are never read.
    """
    rng = random.Random(seed)
    socks = []
    try:
        for _ in range(senders):
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.bind(("127.0.0.1", 0))
            s.setblocking(False)
            socks.append(s)
        t0 = time.monotonic()
        sent = 0
        while True:
            now = time.monotonic()
            if now - t0 >= duration_s:
                break
            due = min(int((now - t0) * rate_hz) + 1, round(duration_s * rate_hz))
            while sent < due:
                i = sent % senders
                try:
                    socks[i].sendto(flood_datagram(kind, i, sent, rng), ("127.0.0.1", port))
                except OSError:
                    pass  # a full socket buffer: the flood is bounded anyway
                sent += 1
            time.sleep(0.002)
        return sent
    finally:
        for s in socks:
            s.close()


# ----- the server ------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Scenario:
    name: str
    kind: str | None  # None: no flood (the baseline)
    senders: int = 1
    signed: bool = False
    rate_hz: float | None = None  # None: the campaign's flood rate


def scenarios() -> list[Scenario]:
    out = [Scenario("none", None), Scenario("truncated, 1/s", "truncated", 1, rate_hz=1.0)]
    for kind in FLOOD_KINDS:
        out.append(Scenario(f"{kind} x1", kind, 1))
        if kind != "bad_crc":
            out.append(Scenario(f"{kind} x10", kind, 10))
    out += [Scenario("signed: none", None, signed=True), Scenario("signed: random x10", "random", 10, True),
            Scenario("signed: truncated, 1/s", "truncated", 1, True, rate_hz=1.0),
            Scenario("signed: command x10", "command", 10, True)]
    return out


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def rss_kb(pid: int) -> int | None:
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    m = re.search(r"^VmRSS:\s+(\d+) kB", text, re.M)
    return int(m.group(1)) if m else None


@dataclass
class Server:
    proc: subprocess.Popen
    port: int
    out: Path
    stderr: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        # Read its stderr as it comes: a full pipe would block the server's logging, and the flood with it.
        threading.Thread(target=lambda: self.stderr.extend(self.proc.stderr), daemon=True).start()

    @property
    def tlog(self) -> Path:
        return self.out / "telemetry.tlog"

    def tlog_bytes(self) -> int:
        try:
            return self.tlog.stat().st_size
        except OSError:
            return 0

    def stop(self) -> str:
        """Stop it (SIGTERM, as an operator's Ctrl-C); its stderr."""
        self.proc.terminate()
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(timeout=5)
        deadline = time.monotonic() + 5.0
        while not self.proc.stderr.closed and time.monotonic() < deadline and not any(
                "stopped after" in line for line in self.stderr):
            time.sleep(0.01)  # the reader thread takes the last lines
        return "".join(self.stderr)


def start_server(workdir: Path, key_file: Path | None, server_path: Path) -> Server:
    port = free_udp_port()
    out = workdir / f"serve-{port}"
    cmd = [sys.executable, "-m", "sitl.cli", "serve", "--vehicle", "kinematic", "--mavlink", f"udp:127.0.0.1:{port}",
           "--p-traj", "20", "--out", str(out)]
    if key_file is not None:
        cmd += ["--signing-key", str(key_file)]
    env = dict(os.environ, PYTHONPATH=str(server_path))
    proc = subprocess.Popen(cmd, cwd=server_path, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)
    return Server(proc, port, out)


# ----- the ground station ----------------------------------------------------------------------------

@dataclass
class Measured:
    """What one flood did to the ground station and the server."""

    scenario: Scenario
    flood_sent: int = 0
    attitude_hz: float = 0.0
    latencies_s: list[float] = field(default_factory=list)
    replies_lost: int = 0
    upload_s: float | None = None
    tlog_growth_kb: float = 0.0
    rss_peak_mb: float = 0.0
    rss_start_mb: float = 0.0
    unsolicited: dict[str, int] = field(default_factory=dict)
    server_dropped: int | None = None
    error: str = ""

    @property
    def latency_median_s(self) -> float:
        return statistics.median(self.latencies_s) if self.latencies_s else math.nan

    @property
    def latency_max_s(self) -> float:
        return max(self.latencies_s) if self.latencies_s else math.nan

    @property
    def meets_targets(self) -> bool:
        return (not self.error and self.attitude_hz >= TARGET_ATTITUDE_HZ and self.replies_lost == 0
                and self.latency_max_s <= TARGET_REPLY_S and self.upload_s is not None
                and not sum(self.unsolicited.values()))


def mission_items(n: int) -> list:
    """n waypoints in the local frame (MISSION_ITEM_INT), home first, for the upload."""
    items = []
    for seq in range(n):
        frame = mavlink.MAV_FRAME_LOCAL_NED
        items.append(mavlink.MAVLink_mission_item_int_message(
            1, 1, seq, frame, mavlink.MAV_CMD_NAV_WAYPOINT, 0, 1, 0, 0, 0, 0, seq * 10_000, seq * 5_000, -3.0, 0))
    return items


class Gcs:
    """A pymavlink ground station that classifies everything it receives."""

    def __init__(self, port: int, key: bytes | None, timeout_s: float = 30.0) -> None:
        self.conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=GCS_SYS,
                                               source_component=GCS_COMP, dialect="ardupilotmega")
        if key is not None:
            self.conn.setup_signing(key, sign_outgoing=True)
        self.attitudes = 0
        self.unsolicited: dict[str, int] = {}
        self._param_asked: dict[int, float] = {}  # param index -> time asked
        self._uploading = False
        self._uploaded = False
        self._upload_wait: float | None = None
        self.latencies_s: list[float] = []
        self.counting = False
        self._last_hb = 0.0
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            self._heartbeat()
            m = self.conn.recv_match(blocking=True, timeout=0.2)
            if m is not None and m.get_type() == "HEARTBEAT" and m.get_srcSystem() == 1:
                return
        raise TimeoutError(f"no HEARTBEAT from serve on port {port} in {timeout_s:g} s")

    def close(self) -> None:
        self.conn.close()

    def _heartbeat(self) -> None:
        now = time.monotonic()
        if now - self._last_hb >= 1.0:
            self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            self._last_hb = now

    def _unsolicited(self, m) -> None:
        key = m.get_type()
        self.unsolicited[key] = self.unsolicited.get(key, 0) + 1

    def poll(self, until: float) -> Iterator:
        """Every message until the monotonic time `until`, classified; yields those a caller may want."""
        while True:
            self._heartbeat()
            left = until - time.monotonic()
            if left <= 0:
                return
            m = self.conn.recv_match(blocking=True, timeout=min(left, 0.05))
            if m is None:
                continue
            kind, now = m.get_type(), time.monotonic()
            if kind == "BAD_DATA":
                continue
            if kind == "ATTITUDE":
                self.attitudes += self.counting
            if kind in TELEMETRY:
                continue
            target = (getattr(m, "target_system", None), getattr(m, "target_component", None))
            if target[0] is not None and target[0] != 0 and target != (GCS_SYS, GCS_COMP):
                if self.counting:
                    self._unsolicited(m)  # a reply meant for another sender
                continue
            if kind == "PARAM_VALUE":
                asked = self._param_asked.pop(m.param_index, None)
                if asked is None:
                    if self.counting:
                        self._unsolicited(m)
                else:
                    self.latencies_s.append(now - asked)
                continue
            if kind in ("MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK") and self._uploading:
                if self._upload_wait is not None:
                    self.latencies_s.append(now - self._upload_wait)
                    self._upload_wait = None
                yield m
                continue
            if kind == "STATUSTEXT" and self._uploaded and m.text.startswith("mission received"):
                continue  # the news of our own upload
            if self.counting:
                self._unsolicited(m)

    def ask_param(self, index: int) -> None:
        self._param_asked[index] = time.monotonic()
        self.conn.mav.param_request_read_send(1, 1, b"", index)

    def lost_params(self, now: float) -> int:
        lost = [i for i, t in self._param_asked.items() if now - t > REPLY_LOST_S]
        for i in lost:
            del self._param_asked[i]
        return len(lost)

    def work(self, duration_s: float, upload_at_s: float, items: list) -> tuple[float | None, int]:
        """Read a parameter every second and upload `items` once, for duration_s; (upload time, replies lost)."""
        t0 = time.monotonic()
        end = t0 + duration_s
        next_read, index, lost = t0, 0, 0
        upload_t0: float | None = None
        upload_s: float | None = None
        while time.monotonic() < end:
            now = time.monotonic()
            lost += self.lost_params(now)
            if now >= next_read:
                self.ask_param(index % 5)
                index += 1
                next_read += 1.0
            if upload_t0 is None and now - t0 >= upload_at_s:
                upload_t0 = self._upload_wait = time.monotonic()
                self._uploading = True
                self.conn.mav.mission_count_send(1, 1, len(items), 0)
            if self._uploading and self._upload_wait is not None and now - self._upload_wait > REPLY_LOST_S:
                lost += 1  # the request / ack never came: upload failed
                self._uploading = False
                self._upload_wait = None
            for m in self.poll(min(next_read, end)):
                if m.get_type() == "MISSION_ACK":
                    self._uploading = False
                    if m.type == mavlink.MAV_MISSION_ACCEPTED:
                        upload_s = time.monotonic() - upload_t0
                        self._uploaded = True
                    break
                if 0 <= m.seq < len(items):
                    self._upload_wait = time.monotonic()
                    self.conn.mav.send(items[m.seq])
        self.counting = False
        lost += len(self._param_asked)  # asked and never answered
        return upload_s, lost


# ----- one scenario ----------------------------------------------------------------------------------

@dataclass(frozen=True)
class CampaignConfig:
    flood_s: float = 6.0
    rate_hz: float = 3000.0
    """Flood datagrams per second, all senders together (the issue measured ~7,000 STATUSTEXT/s)."""
    warmup_s: float = 1.5
    mission_items: int = 20
    server_path: Path = ROOT


def run_scenario(sc: Scenario, cfg: CampaignConfig, workdir: Path, key: bytes | None, key_file: Path | None,
                 say: Callable[[str], None] = lambda _s: None) -> Measured:
    """Start a serve, connect, flood while working, stop; what was measured."""
    res = Measured(sc)
    server = start_server(workdir, key_file if sc.signed else None, cfg.server_path)
    gcs = None
    flooder = None
    try:
        gcs = Gcs(server.port, key if sc.signed else None)
        for _ in gcs.poll(time.monotonic() + cfg.warmup_s):
            pass
        rss = [rss_kb(server.proc.pid) or 0]
        tlog0 = server.tlog_bytes()
        rate_hz = sc.rate_hz or cfg.rate_hz
        if sc.kind is not None:
            flooder = mp.get_context("fork").Process(
                target=flood, args=(server.port, sc.kind, sc.senders, rate_hz, cfg.flood_s))
            flooder.start()
        gcs.counting = True
        t0 = time.monotonic()
        upload_s, lost = gcs.work(cfg.flood_s, upload_at_s=1.0, items=mission_items(cfg.mission_items))
        res.attitude_hz = gcs.attitudes / (time.monotonic() - t0)
        rss.append(rss_kb(server.proc.pid) or 0)
        res.tlog_growth_kb = (server.tlog_bytes() - tlog0) / 1000
        res.upload_s, res.replies_lost = upload_s, lost
        res.latencies_s = gcs.latencies_s
        res.unsolicited = dict(gcs.unsolicited)
        res.rss_start_mb, res.rss_peak_mb = rss[0] / 1024, max(rss) / 1024
        if flooder is not None:
            flooder.join(timeout=cfg.flood_s + 10)
            res.flood_sent = round(rate_hz * cfg.flood_s)
    except (TimeoutError, OSError) as exc:
        res.error = str(exc)
    finally:
        if flooder is not None and flooder.is_alive():
            flooder.terminate()
            flooder.join(timeout=5)
        if gcs is not None:
            gcs.close()
        err = server.stop()
        m = re.search(r"dropped (\d+) malformed datagrams", err)
        res.server_dropped = int(m.group(1)) if m else 0
        if server.proc.returncode not in (0, -15) and not res.error:
            res.error = f"serve exited {server.proc.returncode}: {err.strip().splitlines()[-1:]}"
    say(row(res))
    return res


# ----- MAVProxy connecting ----------------------------------------------------------------------------

@dataclass(frozen=True)
class MavproxyConnect:
    """MAVProxy against a fresh serve: seconds from seeing the vehicle to having every parameter."""

    params_after_online_s: float | None
    fence_breach: bool
    error: str = ""


def mavproxy_connect(workdir: Path, server_path: Path, timeout_s: float = 30.0) -> MavproxyConnect:
    """Start serve and MAVProxy (`--master=udpout:`), time "online system 1" -> "Received N parameters"."""
    exe = shutil.which("mavproxy.py") or str(Path(sys.executable).parent / "mavproxy.py")
    if not Path(exe).exists():
        return MavproxyConnect(None, False, "MAVProxy is not installed")
    server = start_server(workdir, None, server_path)
    lines: queue.Queue = queue.Queue()
    mp_proc = subprocess.Popen([exe, f"--master=udpout:127.0.0.1:{server.port}", "--nowait", "--logfile",
                                str(workdir / "mavproxy.tlog")], cwd=workdir, stdin=subprocess.PIPE,
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    threading.Thread(target=lambda: [lines.put((time.monotonic(), x)) for x in mp_proc.stdout], daemon=True).start()
    online = params = None
    fence = False
    end = time.monotonic() + timeout_s
    try:
        while params is None and time.monotonic() < end:
            try:
                t, line = lines.get(timeout=0.2)
            except queue.Empty:
                continue
            fence |= "fence breach" in line
            if online is None and "online system 1" in line:
                online = t
            if online is not None and re.search(r"Received \d+ parameters", line):
                params = t
    finally:
        mp_proc.terminate()
        try:
            mp_proc.wait(timeout=5)
        except subprocess.TimeoutExpired:  # MAVProxy's module threads can ignore SIGTERM
            mp_proc.kill()
            mp_proc.wait(timeout=5)
        server.stop()
    if params is None:
        return MavproxyConnect(None, fence, f"no parameters within {timeout_s:g} s")
    return MavproxyConnect(params - online, fence)


def mavproxy_line(r: MavproxyConnect) -> str:
    if r.error:
        return f"MAVProxy connecting to `serve`: {r.error}."
    return (f"MAVProxy connecting to `serve` (`--master=udpout:`, no flood): all parameters "
            f"{r.params_after_online_s:.2f} s after \"online system 1\"; \"fence breach\" "
            f"{'printed' if r.fence_breach else 'not printed'}.")


# ----- the report ------------------------------------------------------------------------------------

HEADER = ("| flood | sent | ATTITUDE/s | reply median / max (s) | lost | upload (s) | tlog +kB | RSS MB | "
          "unsolicited | dropped | targets |")
RULE = "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"


def row(r: Measured) -> str:
    if r.error:
        return f"| {r.scenario.name} | | | | | | | | | | error: {r.error} |"
    unsolicited = sum(r.unsolicited.values())
    detail = ", ".join(f"{k} {v}" for k, v in sorted(r.unsolicited.items()))
    upload = f"{r.upload_s:.2f}" if r.upload_s is not None else "failed"
    return (f"| {r.scenario.name} | {r.flood_sent} | {r.attitude_hz:.1f} | {r.latency_median_s:.3f} / "
            f"{r.latency_max_s:.3f} | {r.replies_lost} | {upload} | {r.tlog_growth_kb:.0f} | {r.rss_peak_mb:.0f} | "
            f"{unsolicited}{f' ({detail})' if detail else ''} | {r.server_dropped} | "
            f"{'met' if r.meets_targets else 'MISSED'} |")


def render(results: list[Measured], cfg: CampaignConfig, wall_s: float, mavproxy: MavproxyConnect | None = None) -> str:
    met = sum(r.meets_targets for r in results)
    lines = [
        "## Link campaign: `serve` under hostile MAVLink senders",
        "",
        f"Regenerated by `python -m tools.link_campaign --write docs/reliability.md` ({wall_s:.0f} s). "
        f"Each row: a fresh `pilescan-sitl serve --vehicle kinematic` on loopback; a pymavlink ground station "
        f"connects, then for {cfg.flood_s:g} s another process floods the same port at {cfg.rate_hz:g} "
        f"datagrams/s (from 1 or 10 source ports; the \"1/s\" rows: one datagram a second) while the ground "
        "station reads a parameter every second and "
        f"uploads a {cfg.mission_items}-item mission. Signed rows: the server has `--signing-key` and the ground "
        "station signs; the flooders do not.",
        "",
        "Columns: flood datagrams sent; ATTITUDE/s received by the ground station; latency of its replies "
        "(PARAM_VALUE for each read, each mission request); replies lost (not back within "
        f"{REPLY_LOST_S:g} s); mission upload time; growth of the server's telemetry.tlog during the flood; "
        "server RSS (peak of the samples); messages the ground station received that were neither telemetry nor "
        "an answer to its own requests; datagrams the server dropped as malformed (from its closing line). "
        f"Targets: ATTITUDE >= {TARGET_ATTITUDE_HZ:g}/s, every reply within {TARGET_REPLY_S:g} s, no reply lost, "
        "upload done, no unsolicited message.",
        "",
        HEADER,
        RULE,
        *[row(r) for r in results],
        "",
        f"{met} of {len(results)} rows meet every target. Machine: {os.cpu_count()} CPUs, shared; timings are "
        "wall-clock and vary with the load.",
        *(["", mavproxy_line(mavproxy)] if mavproxy is not None else []),
    ]
    return "\n".join(lines) + "\n"


def make_key_file(workdir: Path) -> tuple[bytes, Path]:
    key = os.urandom(32)
    path = workdir / "campaign.key"
    path.write_text(key.hex() + "\n")
    path.chmod(0o600)
    return key, path


def run(selected: list[Scenario], cfg: CampaignConfig, say: Callable[[str], None] = print,
        with_mavproxy: bool = True) -> tuple[list[Measured], MavproxyConnect | None]:
    with tempfile.TemporaryDirectory(prefix="link-campaign-") as tmp:
        workdir = Path(tmp)
        key, key_file = make_key_file(workdir)
        results = [run_scenario(sc, cfg, workdir, key, key_file, say) for sc in selected]
        mavproxy = None
        if with_mavproxy:
            (workdir / "mavproxy").mkdir()
            mavproxy = mavproxy_connect(workdir / "mavproxy", cfg.server_path)
            say(mavproxy_line(mavproxy))
        return results, mavproxy


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--write", type=Path, default=None, metavar="MD", help="regenerate the section of this file")
    ap.add_argument("--only", default=None, help="run the floods whose name contains this text")
    ap.add_argument("--flood-s", type=float, default=CampaignConfig.flood_s, help="seconds per flood")
    ap.add_argument("--rate", type=float, default=CampaignConfig.rate_hz, help="flood datagrams per second")
    ap.add_argument("--server-path", type=Path, default=ROOT, help="checkout whose serve to measure")
    ap.add_argument("--no-mavproxy", action="store_true", help="skip the MAVProxy connect measurement")
    args = ap.parse_args(argv)
    if not (math.isfinite(args.flood_s) and 0 < args.flood_s <= 60):
        ap.error("--flood-s must be in (0, 60]")
    if not (math.isfinite(args.rate) and 0 < args.rate <= 20_000):
        ap.error("--rate must be in (0, 20000]")
    cfg = CampaignConfig(flood_s=args.flood_s, rate_hz=args.rate, server_path=args.server_path.resolve())
    selected = [s for s in scenarios() if args.only is None or args.only in s.name]
    if not selected:
        ap.error(f"no flood matches {args.only!r}")
    t0 = time.monotonic()
    print(HEADER)
    print(RULE)
    results, mavproxy = run(selected, cfg, with_mavproxy=not args.no_mavproxy)
    section = render(results, cfg, time.monotonic() - t0, mavproxy)
    if args.write is not None:
        write_section(args.write, SECTION, section)
        print(f"wrote {args.write}")
    return 0 if all(r.meets_targets for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
