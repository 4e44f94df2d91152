"""`pilescan-ground listen`: the ground end of the payload's live sample stream (`pilescan-payload --stream`).

Receives the PSLV datagrams (`firmware_py.live_stream`), shows a one-line status about once a second
(records, rate, lost and late datagrams, datagrams refused by reason) and appends the records to a
sample log (`firmware_py.core.samplelog`, the same format the payload writes on the drone), until SIGINT /
SIGTERM or `--duration`; then a summary. The drone's own log stays the record: the stream is UDP, so
datagrams can be lost (counted from sequence gaps), and the live log holds what arrived, in arrival
order (a datagram reordered by the network lands late; a duplicate of an unauthenticated datagram is
written twice, an authenticated one is refused as a replay).

Security: with `key` (`--signing-key FILE`, the payload's key file) only authenticated, fresh
datagrams are taken; unauthenticated, forged (bad tag) and replayed ones are refused and counted.
With `allowed_peers` (`--allow-peer HOST[:PORT]`) datagrams from any other address are refused,
key or not. A receiver without a key takes both formats and does not check tags.

The log header. The stream carries records only, not the payload's header (storage, sensor model,
lever arm, servo: what the report needs to turn records into a volume). So:

- with `--header FILE` (a sample log, e.g. the payload's log of an earlier flight with the same setup
  or a SITL run, or a JSON file holding a header object), that header is written, with a
  ``live_stream`` entry added (where and how the records were received): `pilescan-ground report`
  can then process the live log as it would the drone's;
- without it, a minimal header: ``software``, ``created_utc``, ``source: "live-stream"`` and
  ``live_stream``. `read_samplelog` reads the records; `pilescan-ground report` refuses the log in
  one line (the header lacks the storage geometry) rather than guess a building.

Joining late. UDP keeps no history: what the payload sent before `listen` was up never arrives. The
payload numbers its datagrams from 0 when it starts, so a stream first heard at datagram N had N
datagrams sent before: one line says so when it happens ("joined the stream from HOST:PORT at datagram
15 (about record 300): ..."), the summary's `joined` line repeats it, and `lost` counts them, apart
from those lost in transit (`JoiningReceiver`, within the same loss budget). Records are counted in
datagrams of up to the sender's batch size (partial batches, sent once a second, hold fewer), so the
records before are "up to" N times it. Start `listen` before the payload to have every record.

Under a flood. Loss is counted per sender, within what a sender can plausibly have sent
(`ground.live_receiver`): forged sequence numbers show as resyncs, not as billions of lost
datagrams. The live log has a size cap (`max_log_bytes`, `--max-log-mb`, default
`DEFAULT_MAX_LOG_MIB`: more than an hour at the payload's highest rate, 2000 Hz, and five at its
usual 500 Hz, longer than any battery lasts): records that would take the file past it are not
written (the last block written is whole: the log stays readable), one line says so once, and
receiving and counting go on (`records_unlogged`).

What the records are. The status line and the summary count samples by what their flags say
(`firmware_py.core.flag_tally`): usable, no return (nothing within the sensor's reach: normal
over open floor), faulty (sensor error, stale or missing pose, servo in doubt).

The live page. With `web` (`--web HOST:PORT`) a page on that address shows the survey as it is flown,
updated once a second: coverage map, track, running volume with its interval, unseen cells, these
counters (`ground.live_page`, `ground.live_state`, docs/live.md). The receiver only hands each batch of
records over to the page's threads; it never waits for them.
"""

from __future__ import annotations

import dataclasses
import json
import math
import select
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from firmware_py.core.cli import UserError, stop_on_signals
from firmware_py.core.flag_tally import FlagTally
from firmware_py.core.header import software_version, utc_now_iso
from firmware_py.core.keys import load_key
from firmware_py.core.safe_read import InputError, read_bounded
from firmware_py.core.samplelog import (
    END_BLOCK_MAX_BYTES,
    FORMAT_NAME,
    HEAD_SIZE,
    MAGIC,
    MAX_LOG_BYTES,
    SAMPLE_DTYPE,
    SampleLogWriter,
    read_samplelog,
    rewritable_header,
)
from firmware_py.core.stream_format import parse_stream_url
from ground.live_page import LivePageServer, parse_web_address
from ground.live_receiver import (
    LOSS_GRACE_S,
    MAX_SENDERS,
    RESTART_GAP,
    LiveStreamReceiver,
    PeerSpec,
    SenderKey,
)
from ground.live_state import LiveGeometry, LiveState

PROG = "pilescan-ground listen"
STATUS_PERIOD_S = 1.0
LIVE_SOURCE = "live-stream"
"""``source`` of the minimal header written when no --header is given."""
REFUSAL_REASONS = ("malformed", "rejected_peer", "unauthenticated", "bad_tag", "replayed")
"""`LiveStreamReceiver.stats` keys that count refused datagrams."""
GEOMETRY_KEYS = ("storage", "storage_frame", "lever_arm_body_m", "sensor")
"""Header keys the report needs; a --header without them is written anyway, with a warning."""
_MAX_WAIT_S = 0.25
"""Longest wait for a datagram, so a stop request (signal) is seen promptly."""
MIB = 1 << 20
DEFAULT_MAX_LOG_MIB = 512
"""Default live-log size cap: 2000 Hz x 59 B is 425 MB an hour, 500 Hz 106 MB (module docstring)."""


CONFIRM_RUN = 10
"""A sender's first sequence number is taken as datagrams sent before listen joined only once it has sent this many
in a row, each one more than the last: one forged datagram, or a flood of random numbers, is never counted."""
JOIN_LINES = 3
"""Joins said as they happen (one line each); more (a flood of new senders) are only counted."""


@dataclass
class StreamJoin:
    """Where this listener joined one sender's stream: the sender numbers its datagrams from 0 when it
    starts, so a first datagram numbered N says N were sent before this listener heard any (started
    after the payload, or restarted: UDP keeps no history)."""

    sender: SenderKey
    first_seq: int
    """The lowest sequence number heard from the sender: the datagrams before it were never received."""
    first_t: float
    counted: int = 0
    """How many of them are counted in `lost` so far (`JoiningReceiver`: no more than it could have sent)."""
    last_seq: int = -1
    run: int = 0
    """Datagrams in a row, each numbered one more than the last: a payload's stream does that, a flood of forged
    numbers never does (`CONFIRM_RUN`)."""
    confirmed: bool = False
    batch: int = 0
    """The most records seen in one of its datagrams (its batch size, for the records estimate)."""

    @property
    def records_max(self) -> int:
        """At most this many records were in the datagrams sent before (a partial batch, sent when the
        payload flushes once a second, holds fewer)."""
        return self.first_seq * self.batch

    @property
    def where(self) -> str:
        peer, sender_id = self.sender
        text = f"{peer[0]}:{peer[1]}" if isinstance(peer, tuple) else "an unknown address"
        return text + (f" (sender id {sender_id})" if sender_id is not None else "")


class JoiningReceiver(LiveStreamReceiver):
    """`LiveStreamReceiver`, plus the datagrams each sender sent before its first one heard here.

    The receiver counts gaps between the datagrams it hears; a sender's first datagram numbered N means
    N more, sent before this listener was there to hear them. They are counted in `stats["lost"]` and in
    `stats["joined"]`, as far as the loss budget allows (the receiver's rule: no more than the highest
    rate for as long as the sender has been heard, plus `LOSS_GRACE_S`), and only once the sender has sent
    `CONFIRM_RUN` datagrams in a row, each numbered one more than the last, as a payload does: a forged first
    number, or a flood of random ones, adds nothing, and a real stream joined late is counted in full within
    a second of that (or, joined hours in, as it goes on being heard). A datagram that arrives late, behind the
    first one heard, lowers the count. `joins` holds one `StreamJoin` per sender (bounded as the
    receiver's table); `new_joins` those not yet said (drained by the listener).
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.stats["joined"] = 0
        self.joins: dict[SenderKey, StreamJoin] = {}
        self.new_joins: list[StreamJoin] = []
        self._heard: StreamJoin | None = None

    def feed(self, data: bytes, peer: tuple[str, int] | None = None) -> np.ndarray:
        self._heard = None
        recs = super().feed(data, peer)
        heard = self._heard
        if heard is not None and len(recs) > heard.batch:
            heard.batch = len(recs)
        return recs

    def _track(self, sender: SenderKey, seq: int) -> None:
        late = self.stats["late"]
        super()._track(sender, seq)
        now = self._monotonic()
        join = self.joins.pop(sender, None)
        if join is None:
            if len(self.joins) >= MAX_SENDERS:
                del self.joins[next(iter(self.joins))]  # the least recently heard, as the receiver does
            join = StreamJoin(sender, seq, now)
        elif self.stats["late"] > late and 0 < join.first_seq - seq < RESTART_GAP:
            join.first_seq = seq  # an earlier datagram, reordered behind the first one heard: it was received
            self._recount(join, -max(0, join.counted - seq))
        join.run = join.run + 1 if seq == join.last_seq + 1 else 0
        join.last_seq = seq
        if not join.confirmed and join.run >= CONFIRM_RUN:
            join.confirmed = True
            if join.first_seq:
                self.new_joins.append(join)
        self.joins[sender] = join
        self._heard = join
        if join.confirmed and join.counted < join.first_seq:
            budget = int(self._max_rate_hz * (now - join.first_t + LOSS_GRACE_S))
            self._recount(join, max(0, min(join.first_seq, budget) - join.counted))

    def _recount(self, join: StreamJoin, change: int) -> None:
        join.counted += change
        self.stats["joined"] += change
        self.stats["lost"] += change

    def joined(self) -> tuple[StreamJoin, ...]:
        """The senders heard first at a sequence number above 0 (copies)."""
        return tuple(dataclasses.replace(j) for j in self.joins.values() if j.first_seq and j.confirmed)


def parse_peer(text: str) -> PeerSpec:
    """`--allow-peer` value -> a host (any port) or (host, port): HOST, HOST:PORT, [IPv6] or [IPv6]:PORT
    (an IPv6 address without brackets is a host). ValueError (one line) for anything else."""
    form = "HOST, HOST:PORT or [IPv6]:PORT"
    t = text.strip() if isinstance(text, str) else ""
    host, port = t, None
    if t.startswith("["):
        end = t.find("]")
        rest = t[end + 1:] if end > 0 else None
        if rest is None or (rest and not rest.startswith(":")):
            raise ValueError(f"allowed peer must look like {form}, got {text!r}")
        host, port = t[1:end], (rest[1:] if rest else None)
    elif t.count(":") == 1:
        host, port = t.split(":")
    if not host or any(c.isspace() for c in host):
        raise ValueError(f"allowed peer must look like {form}, got {text!r}")
    if port is None:
        return host
    if not (port.isascii() and port.isdigit() and 1 <= int(port) <= 65535):
        raise ValueError(f"allowed peer port must be 1-65535 in {text!r}")
    return host, int(port)


def load_header(path: str | Path) -> dict[str, Any]:
    """The header in FILE for the live log: a sample log's header, or a JSON object (module docstring).

    Raises:
        UserError: unreadable, neither a sample log with a header nor a JSON object, or a header of
            another log format or record layout (one line naming the file).
    """
    where = f"header file {path}"
    try:  # a regular file, bounded: a FIFO or /dev/zero is refused, not read for ever
        data = read_bounded(path, MAX_LOG_BYTES, "header file")
    except InputError as exc:
        raise UserError(str(exc)) from None
    except OSError as exc:
        raise UserError(f"cannot read {where}: {exc.strerror or exc}") from None
    if data.startswith(MAGIC):
        header = read_samplelog(data).header
        if header is None:
            raise UserError(f"{where} is a sample log whose header is missing or corrupt")
    else:
        try:
            header = json.loads(data.decode("utf-8"))
        except (UnicodeDecodeError, ValueError, RecursionError):
            raise UserError(f"{where} is neither a sample log (.pslog) nor a JSON header object") from None
        if not isinstance(header, dict):
            raise UserError(f"{where} must hold a JSON object (a sample-log header), got {type(header).__name__}")
    if header.get("format", FORMAT_NAME) != FORMAT_NAME:
        raise UserError(f"{where} is a header of another format ({header.get('format')!r})")
    layout = [list(pair) for pair in SAMPLE_DTYPE.descr]
    if "record_dtype" in header and header["record_dtype"] != layout:
        raise UserError(f"{where} describes records of another layout than this version's")
    return rewritable_header(header)


@dataclass(frozen=True)
class ListenConfig:
    """What `listen` is told (CLI options in brackets).

    Attributes:
        url: udp:HOST:PORT to listen on [--stream] (port 0: any free port, for tests; see
            `Listener.local_address`).
        key: the 32-byte link key: take only authenticated, fresh datagrams [--signing-key FILE].
        allowed_peers: take datagrams only from these (host or (host, port)) [--allow-peer]; None: anyone.
        out_path: sample log to write [--out]; None: receive and count only.
        force: overwrite out_path if it exists [--force].
        header: the header to write (reserved keys stripped: `load_header`) [--header]; None: minimal.
        header_from: where `header` came from (recorded in the log).
        duration_s: stop after this long [--duration]; None: until stopped.
        status_period_s: status line period.
        records_per_block: records per fsync'd log block.
        fsync: fsync each block (off only for tests).
        quiet: no status lines or warnings [--quiet].
        max_log_bytes: the live log's size cap [--max-log-mb] (module docstring).
        web: (host, port) to serve the live page on [--web HOST:PORT]; None: no page.
    """

    url: str
    key: bytes | None = field(default=None, repr=False)
    allowed_peers: tuple[PeerSpec, ...] | None = None
    out_path: Path | None = None
    force: bool = False
    header: dict[str, Any] | None = None
    header_from: str | None = None
    duration_s: float | None = None
    status_period_s: float = STATUS_PERIOD_S
    records_per_block: int = 500
    fsync: bool = True
    quiet: bool = False
    max_log_bytes: int = DEFAULT_MAX_LOG_MIB * MIB
    web: tuple[str, int] | None = None

    def __post_init__(self) -> None:
        parse_stream_url(self.url, allow_port_zero=True)
        if isinstance(self.max_log_bytes, bool) or not isinstance(self.max_log_bytes, int) or self.max_log_bytes <= 0:
            raise ValueError(f"log size cap must be a positive number of bytes, got {self.max_log_bytes!r}")
        if self.duration_s is not None and not (math.isfinite(self.duration_s) and self.duration_s > 0):
            raise ValueError(f"--duration must be > 0 s, got {self.duration_s!r}")
        if not (math.isfinite(self.status_period_s) and self.status_period_s > 0):
            raise ValueError(f"status period must be > 0 s, got {self.status_period_s!r}")

    def log_header(self) -> dict[str, Any]:
        """The header the live log gets (module docstring)."""
        live = {"url": self.url, "authenticated": self.key is not None,
                "allowed_peers": None if self.allowed_peers is None else [
                    p if isinstance(p, str) else list(p) for p in self.allowed_peers],
                "received_by": software_version(), "started_utc": utc_now_iso(), "header_from": self.header_from}
        if self.header is None:
            return {"software": software_version(), "created_utc": live["started_utc"], "source": LIVE_SOURCE,
                    "live_stream": live}
        return {**self.header, "live_stream": live}


@dataclass(frozen=True)
class ListenResult:
    """How a `listen` ended and what it received (`stats`: `LiveStreamReceiver.stats`)."""

    url: str
    stop_reason: str
    elapsed_s: float
    records: int
    flagged: int
    stats: dict[str, int]
    authenticated: bool
    out_path: Path | None
    header_from: str | None
    last_refusal: str | None
    warnings: tuple[str, ...] = ()
    samples_text: str = ""
    """The records by what their flags say (`FlagTally.describe`)."""
    records_unlogged: int = 0
    """Records received after the log reached its size cap (counted, not written)."""
    log_cap_bytes: int | None = None
    web_url: str | None = None
    """Where the live page was served (None: no --web)."""
    joins: tuple[StreamJoin, ...] = ()
    """Senders first heard past their first datagram (`JoiningReceiver`): what was sent before listen heard it."""

    @property
    def refused(self) -> dict[str, int]:
        """Refused datagrams by reason (reasons with none left out)."""
        return {k: self.stats[k] for k in REFUSAL_REASONS if self.stats.get(k)}


def _refused_text(refused: dict[str, int]) -> str:
    total = sum(refused.values())
    return f"{total} ({', '.join(f'{k} {v}' for k, v in refused.items())})" if total else "0"


class Listener:
    """Receives the live stream into a sample log. `open()` (or `run()`, which opens if needed), then
    `pump()` by hand or `run()` until `request_stop()` / the duration; `close()` always (idempotent).

    Args:
        cfg: the configuration.
        err: where status lines and warnings go (None: nowhere).
        clock: monotonic seconds (tests may drive it).
    """

    def __init__(self, cfg: ListenConfig, *, err: TextIO | None = sys.stderr,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.cfg, self.err, self.clock = cfg, err, clock
        self.rx: JoiningReceiver | None = None
        self.log: SampleLogWriter | None = None
        self.records = 0
        self.flagged = 0
        self.tally = FlagTally()
        self.records_unlogged = 0
        self._log_full = False
        self._log_bytes = 0
        self._stop_reason: str | None = None
        self._t0: float | None = None
        self._status_prev: tuple[float, int] | None = None
        self._live_line = False
        self._warnings: list[str] = []
        self._warned_unverified = False
        self._joins_said = 0
        self._bound_url: str | None = None
        self.live: LiveState | None = None
        self.page: LivePageServer | None = None

    # ----- control -------------------------------------------------------------------------------

    def request_stop(self, reason: str = "stop requested") -> None:
        """Stop at the next wake-up (at most `_MAX_WAIT_S` away); safe from a signal handler."""
        if self._stop_reason is None:
            self._stop_reason = reason

    @property
    def local_address(self) -> tuple[str, int]:
        if self.rx is None:
            raise ValueError("the listener is not open")
        return self.rx.local_address

    def open(self) -> None:
        """Check the output, bind the socket, create the log (in that order, so nothing is written for a
        port that cannot be had). UserError / ValueError (one line) for anything the user must fix."""
        if self.rx is not None:
            return
        cfg = self.cfg
        out = cfg.out_path
        if out is not None:
            if out.is_dir():
                raise UserError(f"--out {out} is a directory; give a file name such as {out / 'live.pslog'}")
            if out.exists() and not cfg.force:
                raise UserError(f"{out} already exists; choose another --out or pass --force")
            if not out.parent.is_dir():
                raise UserError(f"cannot write {out}: directory {out.parent} does not exist")
        try:
            self.rx = JoiningReceiver(cfg.url, key=cfg.key, allowed_peers=cfg.allowed_peers)
        except OSError as exc:  # address in use, not an address of this machine, name does not resolve
            raise UserError(f"cannot listen on {cfg.url}: {exc.strerror or exc}") from None
        if cfg.web is not None:
            try:
                self._open_page()
            except BaseException:
                self.rx.close()
                self.rx = None
                raise
        if out is not None:
            try:
                self.log = SampleLogWriter(out, cfg.log_header(), records_per_block=cfg.records_per_block,
                                           fsync=cfg.fsync, overwrite=cfg.force)
            except BaseException as exc:
                self.rx.close()
                self.rx = None
                self._close_page()
                if isinstance(exc, OSError):
                    raise UserError(f"cannot write {out}: {exc.strerror or exc}") from None
                raise
        if cfg.header is not None:
            missing = [k for k in GEOMETRY_KEYS if k not in cfg.header]
            if missing:
                self._warn(f"header from {cfg.header_from} lacks {', '.join(missing)}: "
                           f"`pilescan-ground report` will refuse the live log")
        host, port = self.rx.local_address
        self._bound_url = f"udp:[{host}]:{port}" if ":" in host else f"udp:{host}:{port}"
        self._t0 = self.clock()
        self._status_prev = (self._t0, 0)
        if self.page is not None:
            self.live.start()
            if not self.cfg.quiet:
                self._print(f"{PROG}: live page on {self.page.url}")

    def _open_page(self) -> None:
        """The live page's state and server (module docstring); UserError when its address cannot be bound."""
        cfg = self.cfg
        geometry, problem = None, None
        if cfg.header is None:
            problem = "no --header: the building and the sensor's placement are unknown"
        else:
            try:
                geometry = LiveGeometry.from_header(cfg.header, f"header from {cfg.header_from}")
            except UserError as exc:
                problem = str(exc)
        self.live = LiveState(geometry, self.counters, geometry_problem=problem)
        self.page = LivePageServer(*cfg.web, self.live.snapshot_json)

    def _close_page(self) -> None:
        if self.page is not None:
            self.page.close()
        if self.live is not None:
            self.live.close()

    def counters(self) -> dict[str, Any]:
        """What the status line counts, for the live page (read from the page's threads: reads only)."""
        st = self.rx.stats if self.rx is not None else {}
        return {"records": self.records, "datagrams": st.get("datagrams", 0), "lost": st.get("lost", 0),
                "late": st.get("late", 0), "resyncs": st.get("resyncs", 0),
                "refused": sum(st.get(k, 0) for k in REFUSAL_REASONS), "samples": self.tally.describe(),
                "records_unlogged": self.records_unlogged}

    def pump(self, timeout_s: float = 0.0) -> int:
        """Wait up to timeout_s for datagrams, take every one that has arrived, log their records;
        returns how many records were taken (refused datagrams are counted in the receiver's stats)."""
        if self.rx is None:
            raise ValueError("the listener is not open")
        ready, _, _ = select.select([self.rx], [], [], max(0.0, timeout_s))
        if not ready:
            return 0
        recs = self.rx.poll()
        if len(recs):
            if self.log is not None:
                self._log_within_cap(recs)
            self.records += len(recs)
            self.flagged += int(np.count_nonzero(recs["flags"]))
            self.tally.add(recs["flags"])
            if self.live is not None:
                self.live.offer(recs)  # an append: the page's threads do the rest
        if self.rx.new_joins:
            self._say_joins()
        if self.rx.stats["unverified"] and not self._warned_unverified:
            self._warned_unverified = True
            self._warn("the stream is authenticated but this listener has no key (--signing-key): "
                       "its tags are not checked")
        return len(recs)

    def _say_joins(self) -> None:
        """One line for each sender first heard past its first datagram (at most `JOIN_LINES`)."""
        joins, self.rx.new_joins = self.rx.new_joins, []
        for j in joins:
            if self._joins_said < JOIN_LINES:
                self._note(f"joined the stream from {j.where} at datagram {j.first_seq} (about record "
                           f"{j.records_max}): the {j.first_seq} datagrams sent before it, up to {j.records_max} "
                           f"records, were sent before this listener heard them (counted as lost; start listen "
                           f"before the payload to have them)")
            self._joins_said += 1

    def _log_within_cap(self, recs: np.ndarray) -> None:
        """Append what fits under the size cap; the rest is counted. The writer writes whole blocks
        (header, length, CRC, records), so the file never holds half a record."""
        if self._log_full:
            self.records_unlogged += len(recs)
            return
        fits = self._records_that_fit(len(recs))
        if fits:
            self.log.append(recs[:fits])
        if fits < len(recs):
            self._log_full = True
            self.records_unlogged += len(recs) - fits
            self.log.flush()
            self._warn(f"the live log reached its size cap of {self.cfg.max_log_bytes / MIB:g} MiB after "
                       f"{self.log.records_written} records: later records are counted, not written "
                       f"(--max-log-mb raises the cap)")

    def _records_that_fit(self, n: int) -> int:
        """How many of n more records the log can take and stay within the cap once written."""
        try:
            on_disk = self._log_bytes = self.cfg.out_path.stat().st_size
        except OSError:  # renamed or removed under us: the writer's file lives on; the last size known
            on_disk = self._log_bytes
        pending, per_block, size = self.log.records_pending, self.cfg.records_per_block, SAMPLE_DTYPE.itemsize

        def bytes_after(k: int) -> int:
            m = pending + k
            return on_disk + m * size + -(-m // per_block) * HEAD_SIZE + END_BLOCK_MAX_BYTES  # and its close

        if bytes_after(n) <= self.cfg.max_log_bytes:
            return n
        lo, hi = 0, n  # bytes_after grows with k: the largest k that fits
        while lo < hi:
            mid = (lo + hi + 1) // 2
            lo, hi = (mid, hi) if bytes_after(mid) <= self.cfg.max_log_bytes else (lo, mid - 1)
        return lo

    def run(self) -> ListenResult:
        """Receive until `request_stop` or the duration; close; the result. The log is closed (its
        last block written) however this ends."""
        self.open()
        period = self.cfg.status_period_s
        end = None if self.cfg.duration_s is None else self._t0 + self.cfg.duration_s
        next_status = self._t0 + period
        try:
            while self._stop_reason is None:
                now = self.clock()
                if end is not None and now >= end:
                    self.request_stop("duration reached")
                    break
                self.pump(min(_MAX_WAIT_S, next_status - now, math.inf if end is None else end - now))
                now = self.clock()
                if now >= next_status:
                    self._status(now)
                    if self.log is not None:
                        self.log.flush()  # what arrived is on disk within a status period
                    next_status = max(next_status + period, now)
        finally:
            self.close()
        return self.result()

    def close(self) -> None:
        """Close the log (writing its last block) and the socket; safe to call repeatedly."""
        try:
            if self.log is not None:
                self.log.close()
        finally:
            if self.rx is not None:
                self.rx.close()
            self._close_page()
            if self._live_line:
                self._print("")
                self._live_line = False

    # ----- reporting -----------------------------------------------------------------------------

    def result(self) -> ListenResult:
        stats = dict(self.rx.stats) if self.rx is not None else {}
        warnings = list(self._warnings)
        if not stats.get("datagrams"):
            refused = sum(stats.get(k, 0) for k in REFUSAL_REASONS)
            warnings.append("no datagrams accepted" + (f" ({refused} refused)" if refused else "")
                            + ": is the payload streaming to this address (pilescan-payload --stream udp:HOST:PORT)"
                            + (" with the same key?" if self.cfg.key is not None else "?"))
        return ListenResult(
            url=self._bound_url or self.cfg.url, stop_reason=self._stop_reason or "stopped",
            elapsed_s=0.0 if self._t0 is None else self.clock() - self._t0, records=self.records,
            flagged=self.flagged, stats=stats, authenticated=self.cfg.key is not None,
            out_path=self.cfg.out_path, header_from=self.cfg.header_from,
            last_refusal=self.rx.last_error if self.rx is not None else None, warnings=tuple(warnings),
            samples_text=self.tally.describe(), records_unlogged=self.records_unlogged,
            log_cap_bytes=self.cfg.max_log_bytes if self.cfg.out_path is not None else None,
            web_url=self.page.url if self.page is not None else None,
            joins=self.rx.joined() if self.rx is not None else ())

    def status_line(self, now: float) -> str:
        """The one-line status: elapsed, records and rate since the last line, datagrams, losses, refusals."""
        t_prev, n_prev = self._status_prev or (now, self.records)
        rate = (self.records - n_prev) / (now - t_prev) if now > t_prev else 0.0
        self._status_prev = (now, self.records)
        st = self.rx.stats
        refused = {k: st[k] for k in REFUSAL_REASONS if st[k]}
        full = "  LOG FULL" if self._log_full else ""
        return (f"{now - self._t0:6.1f} s  records {self.records} ({rate:.0f}/s; {self.tally.describe()})  "
                f"datagrams {st['datagrams']}  lost {st['lost']}  late {st['late']}  resyncs {st['resyncs']}  "
                f"refused {_refused_text(refused)}{full}")

    def _status(self, now: float) -> None:
        line = self.status_line(now)
        if self.cfg.quiet or self.err is None:
            return
        if _isatty(self.err):  # rewrite one line in a terminal; one line per status in a log file
            self._write(f"\r{PROG}: {line}\x1b[K")
            self._live_line = True
        else:
            self._print(f"{PROG}: {line}")

    def _warn(self, text: str) -> None:
        self._warnings.append(text)
        self._note(f"warning: {text}")

    def _note(self, text: str) -> None:
        """A line of its own (after the status line, if one is being rewritten), unless --quiet."""
        if not self.cfg.quiet:
            if self._live_line:
                self._print("")
                self._live_line = False
            self._print(f"{PROG}: {text}")

    def _print(self, text: str) -> None:
        self._write(text + "\n")

    def _write(self, text: str) -> None:
        if self.err is not None:
            try:
                self.err.write(text)
                self.err.flush()
            except (OSError, ValueError):
                pass  # a closed stderr must not stop the receiving


def _isatty(stream: Any) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, OSError, ValueError):
        return False


def format_summary(res: ListenResult) -> str:
    """The final summary, one fact a line (stdout)."""
    st = res.stats
    rate = res.records / res.elapsed_s if res.elapsed_s > 0 else 0.0
    log = (f"{res.out_path}" + (f" (header from {res.header_from})" if res.header_from
                                else " (minimal header: no storage geometry)")
           if res.out_path is not None else "none (no --out)")
    if res.records_unlogged:
        log += (f"; size cap {res.log_cap_bytes / MIB:g} MiB reached: {res.records_unlogged} records "
                f"received but not written")
    senders = st.get("senders", 0)
    joined = st.get("joined", 0)
    lines = [
        f"listened      {res.elapsed_s:.1f} s on {res.url}" + (" (authenticated)" if res.authenticated else ""),
        f"records       {res.records} in {st.get('datagrams', 0)} datagrams, {rate:.1f}/s"
        + (f": {res.samples_text}" if res.samples_text else ""),
        f"lost          {st.get('lost', 0)} datagrams ("
        + (f"{joined} sent before listen joined, {st.get('lost', 0) - joined} in transit; " if joined else "")
        + f"late {st.get('late', 0)}, sender restarts {st.get('restarts', 0)}"
        + (f", implausible sequence jumps {st['resyncs']} (not counted as lost)" if st.get("resyncs") else "")
        + (f"; from {senders} senders" if senders > 1 else "") + ")",
    ]
    lines += [_joined_text(res)] if res.joins else []
    lines += [f"refused       {_refused_text(res.refused)}"]
    if res.refused and res.last_refusal:
        lines.append(f"last refusal  {res.last_refusal}")
    lines += [f"log           {log}"]
    lines += [f"live page     {res.web_url}"] if res.web_url else []
    lines += [f"stopped       {res.stop_reason}"]
    lines += [f"WARNING: {w}" for w in res.warnings]
    return "\n".join(lines)


def _joined_text(res: ListenResult) -> str:
    """The summary's line on the datagrams sent before listen heard a stream (its first sequence number)."""
    joins = res.joins
    before = sum(j.first_seq for j in joins)
    records = sum(j.records_max for j in joins)
    if len(joins) == 1:
        j = joins[0]
        text = (f"joined        at datagram {before} of the stream from {j.where} (about record {records}): "
                f"{before} earlier datagrams, up to {records} records, not received (sent before listen heard "
                f"the stream)")
    else:
        text = (f"joined        {len(joins)} streams after their start: {before} earlier datagrams, up to "
                f"{records} records, not received (sent before listen heard them)")
    uncounted = before - sum(j.counted for j in joins)
    if uncounted > 0:
        text += (f"; {uncounted} of them not counted as lost (beyond the loss budget of a sender heard this "
                 f"briefly: a forged number cannot inflate the loss)")
    return text


def config_from_args(args: Any) -> ListenConfig:
    """ListenConfig from the parsed `listen` options; one-line UserError / ValueError for bad ones."""
    parse_stream_url(args.stream)  # port 0 is refused here: the payload must know where to send
    if args.duration is not None and args.duration <= 0:
        raise UserError(f"--duration must be > 0 s, got {args.duration:g}")
    peers = tuple(parse_peer(p) for p in args.allow_peer) if args.allow_peer else None
    key = load_key(args.signing_key) if args.signing_key is not None else None
    if args.out is not None and not args.out.strip():
        raise UserError("--out must be a non-empty path")
    header = load_header(args.header) if args.header is not None else None
    cap_mib = getattr(args, "max_log_mb", None)
    if cap_mib is None:
        cap_mib = DEFAULT_MAX_LOG_MIB
    if not (isinstance(cap_mib, int | float) and math.isfinite(cap_mib) and cap_mib * MIB >= 1):
        raise UserError(f"--max-log-mb must be a positive size in MiB, got {cap_mib!r}")
    web = getattr(args, "web", None)
    web = parse_web_address(web) if web is not None else None
    return ListenConfig(url=args.stream.strip(), key=key, allowed_peers=peers, web=web,
                        out_path=Path(args.out) if args.out is not None else None, force=args.force,
                        header=header, header_from=args.header, duration_s=args.duration, quiet=args.quiet,
                        max_log_bytes=int(cap_mib * MIB))


def listen(cfg: ListenConfig, *, err: TextIO | None = sys.stderr) -> ListenResult:
    """Run a `Listener` with SIGINT/SIGTERM routed to its stop (call from the main thread)."""
    listener = Listener(cfg, err=err)
    with stop_on_signals(listener.request_stop):
        return listener.run()
