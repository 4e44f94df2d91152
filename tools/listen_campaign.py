"""Link campaign for the payload's UDP MAVLink link and the ground's `listen`: bounded loopback floods.

    python -m tools.listen_campaign --write docs/reliability.md

Two targets, each flooded (random bytes, truncated headers, bad CRCs, forged sequence numbers; from 1
and from 10 source ports; signed and unsigned) while a legitimate peer talks to it:

(a) the payload's UDP MAVLink link (`firmware_py.hal.mavlink_link.PymavlinkLink("udp:...")`, the
    link `pilescan-payload --mavlink udp:HOST:PORT` listens on), read every 2 ms as the 500 Hz
    payload loop reads it, while an autopilot peer streams ATTITUDE and LOCAL_POSITION_NED at 50 Hz
    each (and the link answers with a 1 Hz HEARTBEAT). Measured: the legitimate messages delivered
    per second, their latency from send to delivery (median, max), those never delivered, the
    link's drop counters, flood datagrams answered (sent back to a flood source: a reflector would
    answer), forged messages delivered, and the process's memory growth.
(b) `pilescan-ground listen` (the real command, in its own process) while a payload
    (`LiveStreamSender`) streams 500 samples/s in 20-record datagrams. Measured: the payload's
    records logged versus sent, the lost counter and the resyncs, datagrams refused, log growth
    (with `--max-log-mb`), and the listener's peak memory (its max RSS).

The floods run in another process, at a bounded rate for a bounded time (options); a full run takes
under two minutes. `--write FILE` regenerates this tool's section of FILE (between the
`<!-- listen-campaign:start -->` and `<!-- listen-campaign:end -->` markers, appended if absent).
Everything is measured, nothing asserted: the numbers are as this machine gave them.
"""

from __future__ import annotations

import argparse
import enum
import multiprocessing as mp
import os
import re
import resource
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.core.cli import ArgumentParser, UserError, finite_float, run_cli
from firmware_py.core.keys import signing_timestamp
from firmware_py.core.samplelog import new_records, read_samplelog
from firmware_py.core.stream_format import encode_datagram
from firmware_py.hal.mavlink_link import PymavlinkLink, heartbeat_msg
from firmware_py.hal.signing import MavlinkSigner, SigningConfig
from firmware_py.live_stream import LiveStreamSender
from tools.doc_sections import markers, write_section

SECTION = "listen-campaign"
START, END = markers(SECTION)
KEY = bytes(range(101, 133))
"""The legitimate peers' key in the signed cases (the flood never has it)."""
ATTACKER_KEY = bytes(range(7, 39))
FORGED_MARK_MS = 0xFFFF_FFFF
"""time_boot_ms of the forged ATTITUDEs, so a delivered one is recognised."""
LEGIT_MARK_X_M = 1234.5
"""x_m of the legitimate payload's records, so they are told apart from flood records in the log."""
AUTOPILOT_RATE_HZ = 50.0
"""ATTITUDE and LOCAL_POSITION_NED each, as ArduPilot streams them to a companion."""
PAYLOAD_TICK_S = 0.002
"""The payload loop reads its link every tick at 500 Hz."""
STREAM_RECORDS_HZ = 500.0
STREAM_RECORDS_PER_DATAGRAM = 20
POOL = 256
"""Distinct flood datagrams generated per case (cycled)."""


class Kind(enum.Enum):
    """What the flood sends."""

    NONE = "none"
    RANDOM = "random bytes"
    TRUNCATED = "truncated headers"
    BAD_CRC = "bad CRCs"
    FORGED_SEQ = "forged sequence numbers"


FLOODS = (Kind.RANDOM, Kind.TRUNCATED, Kind.BAD_CRC, Kind.FORGED_SEQ)


@dataclass(frozen=True)
class Case:
    kind: Kind
    ports: int
    signed: bool
    rate_hz: float | None = None
    """The flood's rate, if not the campaign's (a sparse flood: one datagram a second)."""

    @property
    def name(self) -> str:
        if self.kind is Kind.NONE:
            return f"no flood, {'signed' if self.signed else 'unsigned'}"
        rate = "" if self.rate_hz is None else f", {self.rate_hz:g}/s"
        return f"{self.kind.value}, {self.ports} port{'s' if self.ports > 1 else ''}{rate}, " \
               f"{'signed' if self.signed else 'unsigned'}"


@dataclass(frozen=True)
class Settings:
    seconds: float = 1.5
    rate_hz: float = 4000.0
    """Flood datagrams per second (all source ports together)."""
    max_log_mb: float = 4.0
    seed: int = 1


def cases(ports: tuple[int, ...] = (1, 10)) -> list[Case]:
    """Each flood from 1 and 10 ports, signed and unsigned, beside no flood; and one truncated header a
    second (sparse: the case that stalled a shared stream buffer, where a dense flood fills it quickly)."""
    out = []
    for signed in (False, True):
        out.append(Case(Kind.NONE, 0, signed))
        out += [Case(k, p, signed) for k in FLOODS for p in ports]
        out.append(Case(Kind.TRUNCATED, 1, signed, rate_hz=1.0))
    return out


# ----- flood datagrams ------------------------------------------------------------------------------

def _long_message_id() -> int:
    return next(i for i, c in sorted(mavlink.mavlink_map.items()) if c.unpacker.size >= 255)


def mavlink_flood(kind: Kind, signed: bool, rng: np.random.Generator, n: int = POOL) -> list[bytes]:
    """Datagrams for the MAVLink link. Forged ones claim the autopilot's ids (1, 1); in the signed
    cases they are signed with another key (the attacker has no other)."""
    out: list[bytes] = []
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    if signed:
        MavlinkSigner(SigningConfig(ATTACKER_KEY)).attach(mav)
    long_id = _long_message_id()
    for _ in range(n):
        if kind is Kind.RANDOM:
            data = bytearray(rng.integers(0, 256, int(rng.integers(1, 281)), dtype=np.uint8).tobytes())
            if rng.random() < 0.5:
                data[0] = 0xFD  # a magic byte first: the parser has to look at it
        elif kind is Kind.TRUNCATED:
            data = bytearray([0xFD, 255, 0, 0, int(rng.integers(256)), 1, 1]) + long_id.to_bytes(3, "little")
        elif kind is Kind.BAD_CRC:
            data = bytearray(mavlink.MAVLink_attitude_message(FORGED_MARK_MS, 0, 0, 0, 0, 0, 0).pack(mav))
            data[10 + data[1]] ^= 0x5A  # the CRC's low byte
        elif kind is Kind.FORGED_SEQ:
            mav.seq = int(rng.integers(256))
            data = bytearray(mavlink.MAVLink_attitude_message(FORGED_MARK_MS, 3.0, 3.0, 3.0, 0, 0, 0).pack(mav))
        else:
            raise ValueError(kind)
        out.append(bytes(data))
    return out


def stream_flood(kind: Kind, signed: bool, rng: np.random.Generator, n: int = POOL) -> list[bytes]:
    """Datagrams for `listen`. Forged ones are well-formed, with random sequence numbers: version 1
    (unauthenticated) unsigned, version 2 with another key's tags signed."""
    out: list[bytes] = []
    recs = new_records(STREAM_RECORDS_PER_DATAGRAM)
    recs["t_s"] = -1.0
    for _ in range(n):
        seq = int(rng.integers(1 << 32))
        key = ATTACKER_KEY if signed else None
        stamp = signing_timestamp(time.time()) if signed else 0
        good = encode_datagram(seq, recs, key=key, stamp=stamp, sender_id=0)
        if kind is Kind.RANDOM:
            data = rng.integers(0, 256, int(rng.integers(1, 1401)), dtype=np.uint8).tobytes()
            if rng.random() < 0.5:
                data = b"PSLV" + data[4:]
        elif kind is Kind.TRUNCATED:
            data = good[:int(rng.integers(1, len(good)))]
        elif kind is Kind.BAD_CRC:
            b = bytearray(good)
            b[int(rng.integers(16, len(b)))] ^= 0x5A
            data = bytes(b)
        elif kind is Kind.FORGED_SEQ:
            data = good
        else:
            raise ValueError(kind)
        out.append(data)
    return out


def _flood_process(target: tuple[str, int], pool: list[bytes], ports: int, rate_hz: float, seconds: float,
                   go: Any, results: Any) -> None:
    """Send pool datagrams round-robin from `ports` sockets at rate_hz for seconds; report what was sent
    and what came back to the flood's sockets."""
    socks = []
    for _ in range(ports):
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind(("127.0.0.1", 0))
        s.setblocking(False)
        socks.append(s)
    go.wait(30.0)
    sent = sent_bytes = answered = 0
    t0 = time.monotonic()
    k = 0
    burst_s = 0.005
    while (now := time.monotonic()) < t0 + seconds:
        due = int((now - t0) * rate_hz) + 1  # the first at once
        while sent < due:
            data = pool[k % len(pool)]
            try:
                socks[k % ports].sendto(data, target)
                sent += 1
                sent_bytes += len(data)
            except OSError:
                pass
            k += 1
            if k - sent > 10 * len(pool):
                break
        for s in socks:
            answered += _drain(s)
        time.sleep(burst_s)
    time.sleep(0.3)
    for s in socks:
        answered += _drain(s)
        s.close()
    results.put({"sent": sent, "sent_bytes": sent_bytes, "answered": answered})


def _drain(s: socket.socket) -> int:
    n = 0
    while True:
        try:
            s.recv(65535)
        except OSError:
            return n
        n += 1


class Flood:
    """The flood in its own process (another core than the target's), started and joined by the case."""

    def __init__(self, target: tuple[str, int], pool: list[bytes], ports: int, st: Settings,
                 rate_hz: float | None = None) -> None:
        ctx = mp.get_context("fork")  # before any thread of the case starts
        self.go = ctx.Event()
        self.results = ctx.Queue()
        rate = st.rate_hz if rate_hz is None else rate_hz
        self.proc = ctx.Process(target=_flood_process, daemon=True,
                                args=(target, pool, max(1, ports), rate, st.seconds, self.go, self.results))
        self.proc.start()

    def start(self) -> None:
        self.go.set()

    def finish(self) -> dict[str, int]:
        try:
            res = self.results.get(timeout=30.0)
        finally:
            self.proc.join(timeout=10.0)
            if self.proc.is_alive():
                self.proc.kill()
        return res


def _rss_mb() -> float:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


# ----- (a) the payload's UDP MAVLink link --------------------------------------------------------------

class AutopilotPeer:
    """Streams ATTITUDE and LOCAL_POSITION_NED to the link (signed with the key when given), remembering
    when each left; counts what the link sends back."""

    def __init__(self, target: tuple[str, int], key: bytes | None) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.target = target
        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self.signer = MavlinkSigner(SigningConfig(key)) if key is not None else None
        if self.signer is not None:
            self.signer.attach(self.mav)
        self.sent: dict[tuple[str, int], float] = {}
        self.replies = 0
        self.measuring = False
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def frame(self, msg: Any) -> bytes:
        buf = self.signer.pack(msg, self.mav) if self.signer is not None else msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        return bytes(buf)

    def _run(self) -> None:
        period = 1.0 / AUTOPILOT_RATE_HZ
        n = 0
        t0 = time.monotonic()
        while not self._stop.is_set():
            n += 1
            for msg in (mavlink.MAVLink_attitude_message(n, 0.01, 0.02, 0.03, 0, 0, 0),
                        mavlink.MAVLink_local_position_ned_message(n, 1.0, 2.0, -3.0, 0, 0, 0)):
                data = self.frame(msg)
                with self._lock:
                    if self.measuring:
                        self.sent[(msg.get_type(), n)] = time.monotonic()
                try:
                    self.sock.sendto(data, self.target)
                except OSError:
                    pass
            if n % int(AUTOPILOT_RATE_HZ) == 0:
                try:
                    self.sock.sendto(self.frame(mavlink.MAVLink_heartbeat_message(
                        mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 0, 3)), self.target)
                except OSError:
                    pass
            self.replies += _drain(self.sock)
            self._stop.wait(max(0.0, t0 + n * period - time.monotonic()))

    def start(self) -> None:
        self.thread.start()

    def measure(self, on: bool) -> None:
        with self._lock:
            self.measuring = on

    def stop(self) -> None:
        self._stop.set()
        self.thread.join(timeout=5.0)
        self.replies += _drain(self.sock)
        self.sock.close()


def run_link_case(case: Case, st: Settings) -> dict[str, Any]:
    """One flood against the payload's listening UDP link (module docstring, (a))."""
    rng = np.random.default_rng(st.seed)
    link = PymavlinkLink("udp:127.0.0.1:0", signing=SigningConfig(KEY) if case.signed else None)
    try:
        addr = link.local_address
        flood = Flood(addr, mavlink_flood(case.kind, case.signed, rng), case.ports, st, case.rate_hz) \
            if case.kind is not Kind.NONE else None
        ap = AutopilotPeer(addr, KEY if case.signed else None)
        ap.start()
        deadline = time.monotonic() + 5.0
        while not link.peers and time.monotonic() < deadline:  # the autopilot is heard and admitted first
            link.recv()
            time.sleep(PAYLOAD_TICK_S)
        rss0 = _rss_mb()
        got: dict[tuple[str, int], float] = {}
        forged = 0
        ap.measure(True)
        if flood is not None:
            flood.start()
        t0 = time.monotonic()
        next_hb = t0
        rss_max = rss0
        end = t0 + st.seconds
        drain_end = end + 0.5  # messages sent before the end may still be on their way
        tick = t0
        while (now := time.monotonic()) < drain_end:
            if now >= end:
                ap.measure(False)
            for m in link.recv():
                kind = m.get_type()
                if kind in ("ATTITUDE", "LOCAL_POSITION_NED"):
                    if m.time_boot_ms == FORGED_MARK_MS:
                        forged += 1
                    else:
                        got.setdefault((kind, m.time_boot_ms), time.monotonic())
            if now >= next_hb:
                link.send(heartbeat_msg())
                next_hb += 1.0
                rss_max = max(rss_max, _rss_mb())
            tick += PAYLOAD_TICK_S
            time.sleep(max(0.0, tick - time.monotonic()))
        flood_res = flood.finish() if flood is not None else {"sent": 0, "sent_bytes": 0, "answered": 0}
        ap.stop()
    finally:
        link.close()
    lat = [got[k] - t for k, t in ap.sent.items() if k in got]
    stats = link.stats
    return {
        "case": case.name, "flood_sent": flood_res["sent"], "flood_rate": flood_res["sent"] / st.seconds,
        "legit_sent": len(ap.sent), "legit_delivered": len(lat), "legit_rate": len(lat) / st.seconds,
        "lat_median_ms": 1e3 * statistics.median(lat) if lat else None,
        "lat_max_ms": 1e3 * max(lat) if lat else None,
        "dropped_legit": len(ap.sent) - len(lat),
        "bad_frames": stats["rx_bad_frames"], "truncated": stats["rx_truncated"],
        "refused_auth": stats["rx_unsigned"] + stats["rx_bad_signature"] + stats["rx_replayed"],
        "peers_refused": stats["rx_peers_refused"], "peers": len(link.peers),
        "flood_answered": flood_res["answered"], "forged_delivered": forged,
        "autopilot_replies": ap.replies, "rss_growth_mb": rss_max - rss0,
    }


# ----- (b) pilescan-ground listen ---------------------------------------------------------------------

def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _port_taken(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return True
        return False


def _legit_records(n: int, t0: float) -> np.ndarray:
    r = new_records(n)
    r["t_s"] = t0 + np.arange(n) / STREAM_RECORDS_HZ
    r["range_m"] = 5.0
    r["x_m"] = LEGIT_MARK_X_M
    return r


def _summary_int(pattern: str, text: str) -> int | None:
    m = re.search(pattern, text)
    return int(m.group(1)) if m else None


def run_listen_case(case: Case, st: Settings, workdir: Path) -> dict[str, Any]:
    """One flood against `pilescan-ground listen` in its own process (module docstring, (b))."""
    rng = np.random.default_rng(st.seed)
    port = _free_port()
    out = workdir / f"live-{port}.pslog"
    cmd = [sys.executable, "-m", "ground.cli", "listen", "--stream", f"udp:127.0.0.1:{port}", "--out", str(out),
           "--duration", f"{st.seconds + 60:g}", "--max-log-mb", f"{st.max_log_mb:g}"]  # (a backstop: SIGINT ends it)
    if case.signed:
        key_file = workdir / "link.key"
        if not key_file.exists():
            key_file.write_text(KEY.hex() + "\n")
            key_file.chmod(0o600)
        cmd += ["--signing-key", str(key_file)]
    flood = Flood(("127.0.0.1", port), stream_flood(case.kind, case.signed, rng), case.ports, st, case.rate_hz) \
        if case.kind is not Kind.NONE else None
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(Path(__file__).resolve().parents[1]),
                                                                       os.environ.get("PYTHONPATH")]))}
    out_txt, err_txt = workdir / f"listen-{port}.out", workdir / f"listen-{port}.err"
    with open(out_txt, "w") as fo, open(err_txt, "w") as fe:
        proc = subprocess.Popen(cmd, stdout=fo, stderr=fe, env=env)
    try:
        deadline = time.monotonic() + 30.0
        while not _port_taken(port) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        sender = LiveStreamSender(f"udp:127.0.0.1:{port}", STREAM_RECORDS_PER_DATAGRAM,
                                  key=KEY if case.signed else None)
        if flood is not None:
            flood.start()
        t0 = time.monotonic()
        n = 0
        while (now := time.monotonic()) < t0 + st.seconds:
            due = int((now - t0) * STREAM_RECORDS_HZ)
            if due > n:
                sender.append(_legit_records(due - n, n / STREAM_RECORDS_HZ))
                n = due
            time.sleep(PAYLOAD_TICK_S)
        sender.close()
        flood_res = flood.finish() if flood is not None else {"sent": 0, "sent_bytes": 0, "answered": 0}
        time.sleep(0.3)  # the last datagrams reach the listener (it reads within 0.25 s)
        proc.send_signal(signal.SIGINT)  # its Ctrl-C: a clean stop with the summary
        _, status, usage = os.wait4(proc.pid, 0)  # (not proc.wait(): wait4 gives this child's own max RSS)
        proc.returncode = os.waitstatus_to_exitcode(status)
    except BaseException:
        proc.kill()
        raise
    stdout, stderr = out_txt.read_text(), err_txt.read_text()
    max_rss_mb = usage.ru_maxrss / 1024.0
    log = read_samplelog(out) if out.exists() else None
    legit_logged = int(np.count_nonzero(log.samples["x_m"] == np.float32(LEGIT_MARK_X_M))) if log else 0
    return {
        "case": case.name, "exit": proc.returncode, "flood_sent": flood_res["sent"],
        "flood_mb": flood_res["sent_bytes"] / 1e6,
        "legit_sent": sender.stats["records"], "legit_logged": legit_logged,
        "records": _summary_int(r"records\s+(\d+)", stdout), "lost": _summary_int(r"lost\s+(\d+)", stdout),
        "resyncs": _summary_int(r"implausible sequence jumps (\d+)", stdout) or 0,
        "refused": _summary_int(r"refused\s+(\d+)", stdout),
        "unlogged": _summary_int(r"(\d+) records received but not written", stdout) or 0,
        "log_mb": out.stat().st_size / 1e6 if out.exists() else 0.0, "log_intact": bool(log and log.intact),
        "cap_lines": stderr.count("size cap of"), "max_rss_mb": max_rss_mb,
        "flood_answered": flood_res["answered"],
    }


# ----- the page ---------------------------------------------------------------------------------------

def _f(v: Any, fmt: str = "{:.0f}") -> str:
    return "—" if v is None else fmt.format(v)


def link_table(rows: list[dict[str, Any]]) -> str:
    head = ("| flood | flood datagrams/s | legit delivered/s (sent 100/s) | latency median / max [ms] | legit "
            "never delivered | bad frames / truncated / refused (auth) | flood sources answered | forged "
            "delivered | peers (refused) | RSS growth [MB] |\n|---|---|---|---|---|---|---|---|---|---|")
    lines = [head]
    for r in rows:
        lines.append(
            f"| {r['case']} | {r['flood_rate']:,.0f} | {r['legit_rate']:.1f} | {_f(r['lat_median_ms'], '{:.1f}')} / "
            f"{_f(r['lat_max_ms'], '{:.1f}')} | {r['dropped_legit']} | {r['bad_frames']:,} / {r['truncated']:,} / "
            f"{r['refused_auth']:,} | {r['flood_answered']} | {r['forged_delivered']:,} | {r['peers']} "
            f"({r['peers_refused']:,}) | {r['rss_growth_mb']:.1f} |")
    return "\n".join(lines)


def listen_table(rows: list[dict[str, Any]]) -> str:
    head = ("| flood | flood datagrams (MB) | payload records logged / sent | records received (all) | lost | "
            "resyncs | refused | log [MB] (intact) | cap lines | listen max RSS [MB] |\n"
            "|---|---|---|---|---|---|---|---|---|---|")
    lines = [head]
    for r in rows:
        lines.append(
            f"| {r['case']} | {r['flood_sent']:,} ({r['flood_mb']:.1f}) | {r['legit_logged']:,} / {r['legit_sent']:,} "
            f"| {_f(r['records'], '{:,}')} | {_f(r['lost'], '{:,}')} | {r['resyncs']:,} | {_f(r['refused'], '{:,}')} "
            f"| {r['log_mb']:.2f} ({'yes' if r['log_intact'] else 'NO'}) | {r['cap_lines']} "
            f"| {_f(r['max_rss_mb'], '{:.0f}')} |")
    return "\n".join(lines)


def section(link_rows: list[dict[str, Any]], listen_rows: list[dict[str, Any]], st: Settings, wall_s: float,
            write_path: str) -> str:
    lat = [r["lat_max_ms"] for r in link_rows if r["lat_max_ms"] is not None]
    parts = [
        "## Link campaign: the payload's UDP MAVLink link and `pilescan-ground listen`",
        "",
        f"Regenerate with `python -m tools.listen_campaign --write {write_path}` ({wall_s:.0f} s). Loopback "
        f"only; each flood runs {st.seconds:g} s at {st.rate_hz:,.0f} datagrams/s (all source ports together) "
        "from another process, cycling 256 generated datagrams (seed "
        f"{st.seed}). *Signed*: the legitimate peers share a key and the target has it; the flood signs "
        "with another key (forged frames) or not at all. Forged MAVLink frames claim the autopilot's "
        "system and component; forged stream datagrams are well-formed with random sequence numbers.",
        "",
        "**(a) The payload's UDP MAVLink link** (`--mavlink udp:HOST:PORT`), read every 2 ms as the 500 Hz "
        "loop reads it, while an autopilot streams ATTITUDE and LOCAL_POSITION_NED at 50 Hz each. *Legit "
        "never delivered* counts the autopilot's messages that did not come out of the link within 0.5 s "
        "of the flood's end; *flood sources answered* counts datagrams the link sent to a flood socket; "
        "*forged delivered*: forged frames handed to the payload (unsigned, a well-formed frame is "
        "indistinguishable from the autopilot's: only signing stops it); *peers*: senders the link answers.",
        "",
        link_table(link_rows),
        "",
        f"Largest latency of a legitimate message over all cases: {max(lat):.1f} ms." if lat else "",
        "",
        "**(b) `pilescan-ground listen`** (the command, in its own process, with "
        f"`--max-log-mb {st.max_log_mb:g}`), while a payload streams 500 samples/s in 20-record datagrams. "
        "*Payload records logged / sent*: the payload's records found in the live log; *records received*: "
        "what the summary counts, flood records included (unsigned, a well-formed datagram is taken: use "
        "`--signing-key` or `--allow-peer`); *lost* and *resyncs* as the summary gives them (implausible "
        "sequence jumps are resyncs, not losses); *cap lines*: the one-line message at the size cap.",
        "",
        listen_table(listen_rows),
    ]
    return "\n".join(p for p in parts if p is not None) + "\n"


# ----- command line -----------------------------------------------------------------------------------

def build_parser() -> ArgumentParser:
    ap = ArgumentParser(prog="python -m tools.listen_campaign", description=__doc__.split("\n\n")[0])
    ap.add_argument("--write", type=Path, default=None, help="regenerate this tool's section of this page")
    ap.add_argument("--seconds", type=finite_float, default=Settings.seconds, help="flood length per case, s")
    ap.add_argument("--rate", type=finite_float, default=Settings.rate_hz,
                    help="flood datagrams per second, all source ports together")
    ap.add_argument("--max-log-mb", type=finite_float, default=Settings.max_log_mb,
                    help="listen's --max-log-mb in the campaign")
    ap.add_argument("--seed", type=int, default=Settings.seed)
    ap.add_argument("--only", choices=("link", "listen"), default=None, help="one target only")
    return ap


def _body(args: argparse.Namespace) -> int:
    if not 0.2 <= args.seconds <= 30:
        raise UserError(f"--seconds must be 0.2-30, got {args.seconds:g}")
    if not 1 <= args.rate <= 50_000:
        raise UserError(f"--rate must be 1-50000 datagrams/s, got {args.rate:g}")
    if not args.max_log_mb > 0:
        raise UserError(f"--max-log-mb must be > 0, got {args.max_log_mb:g}")
    if args.write is not None and not args.write.parent.is_dir():
        raise UserError(f"--write {args.write}: the directory must exist")
    st = Settings(seconds=args.seconds, rate_hz=args.rate, max_log_mb=args.max_log_mb, seed=args.seed)
    t0 = time.perf_counter()
    link_rows: list[dict[str, Any]] = []
    listen_rows: list[dict[str, Any]] = []
    all_cases = cases()
    if args.only in (None, "link"):
        for i, c in enumerate(all_cases, 1):
            print(f"[link {i}/{len(all_cases)}] {c.name}", file=sys.stderr, flush=True)
            link_rows.append(run_link_case(c, st))
    if args.only in (None, "listen"):
        with tempfile.TemporaryDirectory() as tmp:
            os.chmod(tmp, 0o700)
            for i, c in enumerate(all_cases, 1):
                print(f"[listen {i}/{len(all_cases)}] {c.name}", file=sys.stderr, flush=True)
                listen_rows.append(run_listen_case(c, st, Path(tmp)))
    text = section(link_rows, listen_rows, st, time.perf_counter() - t0,
                   str(args.write) if args.write else "docs/reliability.md")
    print(text)
    if args.write is not None:
        write_section(args.write, SECTION, text)
    return 0


def main(argv: list[str] | None = None) -> int:
    return run_cli(build_parser(), argv, _body)


if __name__ == "__main__":
    raise SystemExit(main())
