"""Benewake TFMini-family LiDAR on a UART: frames parsed, checked and time-stamped.

Wire format (TFmini, TFmini-S, TFmini Plus and TF-Luna manuals): 115200 baud 8N1 by default, one frame
every 1/f s (f = 100 Hz by default, 1000/n Hz settable) of 9 bytes, multi-byte values little-endian:

    0x59 0x59 DIST_L DIST_H STRENGTH_L STRENGTH_H AUX_L AUX_H CHECKSUM

CHECKSUM is the low byte of the sum of the first 8 bytes. AUX is the chip temperature on the S, Plus
and Luna (deg C = AUX / 8 - 256) and the distance mode plus a spare byte on the original TFmini.

What a frame means differs by model (`TfminiVariant`):
- TFmini-S, TFmini Plus, TF-Luna: DIST in cm, signed: -1 when STRENGTH < 100 (the echo is too weak to
  trust), -2 with STRENGTH 65535 (signal saturated), -4 (ambient light saturated).
- TFmini (SJ-PM-TFmini-T-01): DIST 0xFFFF when STRENGTH < 20, and 1200 cm when the target is beyond
  12 m with a usable strength; ArduPilot's Benewake driver likewise takes a reading equal to the
  model's maximum as out of range. Its manual trusts STRENGTH 20-2000 only.
Every such case, and any distance outside the model's range, is a NO_RETURN reading: the part is
working and saw nothing it can vouch for. A frame with a wrong checksum is dropped and counted (the
parser resynchronises on the next 0x59 0x59), never turned into a range: its slot in the stream is
a BUS_ERROR reading (`bad_frames`), so the payload logs one sample per frame the part sent, flagged
when the frame was lost.

Timing: the part streams; the driver never triggers it. `read()` waits for the next frame with a
deadline, polling the port every `poll_interval_ns`. Each read from the port is stamped with the
clock, and a frame's last byte is placed at that stamp minus the bytes that followed it in the same
read (10 bits a byte at the baud rate); its first byte 9 byte times earlier. Older frames of a backlog
(the loop was late) step back one frame period each. The measurement instant is the first byte minus
`output_latency_ns`, a per-part constant the manuals do not give (0 by default: calibrate it on the
bench). The stamping error is at most one poll interval plus the kernel's UART delivery latency.
"""

from __future__ import annotations

import collections
import logging
from dataclasses import asdict, dataclass
from enum import Enum

from firmware_py.core.sensor import TFMINI_S
from firmware_py.drivers.reading import Reading, ReadStatus
from firmware_py.hal import Clock
from firmware_py.hal.uart import DEFAULT_BAUD, STANDARD_BAUDS, SerialPort

log = logging.getLogger(__name__)

HEADER = 0x59
FRAME_LEN = 9
BITS_PER_BYTE = 10  # 8N1: a start bit, 8 data bits, a stop bit


@dataclass(frozen=True)
class TfminiVariant:
    """How one model of the family encodes its readings (module docstring).

    Attributes:
        name: the model, as the user names it (`--rangefinder`).
        min_range_m, max_range_m: the manual's operating range (90 % reflective board, indoors).
        weak_strength: below this STRENGTH the reading is not trusted.
        max_strength: above this STRENGTH neither (None: only the saturation code).
        signed_dist: DIST is a signed int16 with negative codes (S / Plus / Luna), not 0xFFFF (TFmini).
        max_is_out_of_range: a DIST equal to the maximum means "beyond range" (the original TFmini).
    """

    name: str
    min_range_m: float
    max_range_m: float
    weak_strength: int
    max_strength: int | None
    signed_dist: bool
    max_is_out_of_range: bool


class TfminiModel(Enum):
    """The family members this driver knows (their manuals)."""

    TFMINI = TfminiVariant("tfmini", 0.3, 12.0, 20, 2000, signed_dist=False, max_is_out_of_range=True)
    TFMINI_S = TfminiVariant("tfmini-s", 0.1, 12.0, 100, None, signed_dist=True, max_is_out_of_range=False)
    TFMINI_PLUS = TfminiVariant("tfmini-plus", 0.1, 12.0, 100, None, signed_dist=True, max_is_out_of_range=False)
    TF_LUNA = TfminiVariant("tf-luna", 0.2, 8.0, 100, None, signed_dist=True, max_is_out_of_range=False)

    @classmethod
    def named(cls, name: str) -> TfminiModel:
        """The model called `name` (ValueError listing the known names)."""
        for m in cls:
            if m.value.name == name:
                return m
        raise ValueError(f"unknown TFMini model {name!r} (known: {', '.join(m.value.name for m in cls)})")


def checksum(frame: bytes | bytearray) -> int:
    """The low byte of the sum of a frame's first 8 bytes."""
    return sum(frame[:8]) & 0xFF


def encode_frame(dist_cm: int, strength: int, aux: int = 0) -> bytes:
    """One frame (what the part sends; the SITL's emulator and the tests build frames with it).
    `dist_cm` may be a negative code (-1, -2, -4): it is sent as a 16-bit two's complement."""
    body = bytes((HEADER, HEADER, dist_cm & 0xFF, (dist_cm >> 8) & 0xFF, strength & 0xFF, (strength >> 8) & 0xFF,
                  aux & 0xFF, (aux >> 8) & 0xFF))
    return body + bytes((checksum(body),))


@dataclass(frozen=True, slots=True)
class Frame:
    """One checked frame: raw DIST (unsigned 16 bits as sent), STRENGTH, AUX."""

    dist_raw: int
    strength: int
    aux: int

    @classmethod
    def from_bytes(cls, b: bytes | bytearray) -> Frame:
        return cls(b[2] | b[3] << 8, b[4] | b[5] << 8, b[6] | b[7] << 8)


def classify(frame: Frame, variant: TfminiVariant) -> tuple[float | None, ReadStatus]:
    """(range in m, status) of one frame for one model (module docstring): OK or NO_RETURN."""
    dist = frame.dist_raw
    if variant.signed_dist and dist >= 0x8000:
        return None, ReadStatus.NO_RETURN  # -1 weak, -2 saturated, -4 ambient light: no range to trust
    if not variant.signed_dist and dist == 0xFFFF:
        return None, ReadStatus.NO_RETURN
    if frame.strength < variant.weak_strength or (variant.max_strength is not None
                                                   and frame.strength > variant.max_strength):
        return None, ReadStatus.NO_RETURN
    range_m = dist / 100.0
    if variant.max_is_out_of_range and range_m >= variant.max_range_m:
        return None, ReadStatus.NO_RETURN
    if not variant.min_range_m <= range_m <= variant.max_range_m:
        return None, ReadStatus.NO_RETURN
    return range_m, ReadStatus.OK


class FrameParser:
    """Bytes in, checked frames out, each with the index (in the bytes fed) of its last byte.

    Resynchronises on 0x59 0x59 after garbage or a bad checksum; holds at most one frame's worth of
    bytes between calls, so no input can grow it.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self.frames = 0
        self.bad_checksums = 0
        self.skipped_bytes = 0
        self.bad_ends: list[int] = []
        """Of the last `feed`: the index in its data of the last byte of each frame lost to a bad checksum
        (one per corruption: failed checks that start inside the previous failed frame are one loss)."""

    def feed(self, data: bytes) -> list[tuple[Frame, int]]:
        """Frames completed by `data`, with the index in `data` of each one's last byte."""
        held = len(self._buf)
        buf = self._buf
        buf += data
        out: list[tuple[Frame, int]] = []
        bad: list[int] = []
        last_bad = -FRAME_LEN
        i = 0
        while len(buf) - i >= 2:
            if buf[i] != HEADER or buf[i + 1] != HEADER:
                j = buf.find(b"\x59\x59", i + 1)
                if j < 0:  # no header left; a trailing 0x59 may be the first half of the next one
                    j = len(buf) - 1 if buf[-1] == HEADER else len(buf)
                self.skipped_bytes += j - i
                i = j
                continue
            if len(buf) - i < FRAME_LEN:
                break
            frame = buf[i:i + FRAME_LEN]
            if frame[8] != checksum(frame):
                self.bad_checksums += 1
                self.skipped_bytes += 1
                end = i + FRAME_LEN - 1 - held
                if bad and i < last_bad + FRAME_LEN:
                    bad[-1] = end  # the same corruption, seen from a later header: one frame lost
                else:
                    bad.append(end)
                last_bad = i
                i += 1  # the header may have been data: look again one byte on
                continue
            self.frames += 1
            out.append((Frame.from_bytes(frame), i + FRAME_LEN - 1 - held))
            i += FRAME_LEN
        del buf[:i]
        self.bad_ends = bad
        return out

    def reset(self) -> None:
        """Forget the bytes held (the port's input was discarded)."""
        self._buf.clear()


@dataclass(frozen=True)
class TfminiConfig:
    """Driver settings.

    Attributes:
        model: which family member is fitted (how to read its frames).
        baud: the UART rate the part is set to (115200 from the factory).
        frame_rate_hz: the part's output rate (100 Hz from the factory; 1000/n Hz settable).
        output_latency_ns: from the measurement to the frame's first byte (module docstring).
        poll_interval_ns: how often the port is read while waiting for a frame.
        timeout_ns: give up waiting this long (None: three frame periods).
        max_backlog: frames kept when the loop falls behind; older ones are dropped (counted).
    """

    model: TfminiModel = TfminiModel.TFMINI_S
    baud: int = DEFAULT_BAUD
    frame_rate_hz: float = TFMINI_S.rate_hz
    output_latency_ns: int = 0
    poll_interval_ns: int = 100_000
    timeout_ns: int | None = None
    max_backlog: int = 32

    def __post_init__(self) -> None:
        if not isinstance(self.model, TfminiModel):
            raise ValueError(f"model must be a TfminiModel, got {self.model!r}")
        if self.baud not in STANDARD_BAUDS:
            raise ValueError(f"baud must be a standard rate ({', '.join(map(str, STANDARD_BAUDS))}), got {self.baud!r}")
        if not (isinstance(self.frame_rate_hz, int | float) and 1.0 <= self.frame_rate_hz <= 1000.0):
            raise ValueError(f"frame rate must be 1-1000 Hz, got {self.frame_rate_hz!r}")
        wire_s = FRAME_LEN * BITS_PER_BYTE / self.baud
        if wire_s > 1.0 / self.frame_rate_hz:
            raise ValueError(f"{self.frame_rate_hz:g} Hz frames do not fit in {self.baud} baud "
                             f"({wire_s * 1e3:.2f} ms a frame): raise the baud rate")
        for name in ("output_latency_ns", "poll_interval_ns"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0 or (name == "poll_interval_ns" and v == 0):
                raise ValueError(f"{name} must be a non-negative integer (poll interval > 0), got {v!r}")
        if self.timeout_ns is not None and (isinstance(self.timeout_ns, bool) or not isinstance(self.timeout_ns, int)
                                            or self.timeout_ns <= 0):
            raise ValueError(f"timeout_ns must be a positive integer or None, got {self.timeout_ns!r}")
        if isinstance(self.max_backlog, bool) or not isinstance(self.max_backlog, int) or self.max_backlog < 1:
            raise ValueError(f"max_backlog must be a positive integer, got {self.max_backlog!r}")

    @property
    def period_ns(self) -> int:
        return round(1e9 / self.frame_rate_hz)

    @property
    def byte_ns(self) -> int:
        return round(BITS_PER_BYTE * 1e9 / self.baud)

    @property
    def deadline_ns(self) -> int:
        return self.timeout_ns if self.timeout_ns is not None else 3 * self.period_ns


@dataclass(frozen=True, slots=True)
class TfminiCounters:
    """What the driver has counted (a frozen snapshot)."""

    frames: int = 0
    ok: int = 0
    no_return: int = 0
    timeouts: int = 0
    bus_errors: int = 0
    bad_frames: int = 0
    bad_checksums: int = 0
    skipped_bytes: int = 0
    dropped_backlog: int = 0

    @property
    def readings(self) -> int:
        return self.ok + self.no_return + self.timeouts + self.bus_errors

    @property
    def sensor_errors(self) -> int:
        return self.timeouts + self.bus_errors

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class Tfmini:
    """A TFMini-family LiDAR on a serial port (module docstring). `read()` once a tick."""

    def __init__(self, port: SerialPort, clock: Clock, config: TfminiConfig | None = None) -> None:
        self.port, self.clock = port, clock
        self.config = config or TfminiConfig()
        self.variant = self.config.model.value
        self._parser = FrameParser()
        self._backlog: collections.deque[tuple[int, Frame | None]] = collections.deque()
        self._counts = dict.fromkeys(("ok", "no_return", "timeouts", "bus_errors", "bad_frames", "dropped_backlog"),
                                     0)
        self.last_error: OSError | None = None
        self.bytes_read = 0

    def counters(self) -> TfminiCounters:
        p = self._parser
        return TfminiCounters(frames=p.frames, bad_checksums=p.bad_checksums, skipped_bytes=p.skipped_bytes,
                              **self._counts)

    def read(self) -> Reading:
        """The next frame as a reading, waiting for it up to the deadline (TIMEOUT if none came)."""
        cfg = self.config
        start = self.clock.now_ns()
        deadline = start + cfg.deadline_ns
        polls = 0
        while True:
            polls += 1
            try:
                self._drain()
            except OSError as exc:  # pyserial's SerialException is an OSError: an unplugged adapter
                self.last_error = exc
                self._counts["bus_errors"] += 1
                log.debug("TFMini serial read failed: %s", exc)
                return Reading(None, ReadStatus.BUS_ERROR, self.clock.now_ns(), polls)
            if self._backlog:
                t_ns, frame = self._backlog.popleft()
                if frame is None:  # a frame lost to a bad checksum: its slot is a failed reading
                    self._counts["bus_errors"] += 1
                    self._counts["bad_frames"] += 1
                    return Reading(None, ReadStatus.BUS_ERROR, t_ns, polls)
                range_m, status = classify(frame, self.variant)
                self._counts["ok" if status is ReadStatus.OK else "no_return"] += 1
                return Reading(range_m, status, t_ns, polls)
            now = self.clock.now_ns()
            if now >= deadline:
                self._counts["timeouts"] += 1
                return Reading(None, ReadStatus.TIMEOUT, now, polls)
            self.clock.sleep_until_ns(min(now + cfg.poll_interval_ns, deadline))

    def _drain(self) -> None:
        data = self.port.read(4096)
        if not data:
            return
        self.bytes_read += len(data)
        t_read = self.clock.now_ns()
        parser = self._parser
        found: list[tuple[Frame | None, int]] = parser.feed(data)
        if parser.bad_ends:
            found = sorted(found + [(None, end) for end in parser.bad_ends], key=lambda e: e[1])
        if not found:
            return
        cfg = self.config
        byte_ns, period_ns = cfg.byte_ns, cfg.period_ns
        first_offset = (FRAME_LEN - 1) * byte_ns + cfg.output_latency_ns
        newest_last_byte = t_read - (len(data) - 1 - found[-1][1]) * byte_ns
        n = len(found)
        for k, (frame, _) in enumerate(found):
            t_last = newest_last_byte - (n - 1 - k) * period_ns  # a backlog steps back a frame period each
            if len(self._backlog) == cfg.max_backlog:
                self._backlog.popleft()
                self._counts["dropped_backlog"] += 1
            self._backlog.append((t_last - first_offset, frame))

    def discard_input(self, max_bytes: int = 1 << 20) -> int:
        """Throw away what waits in the port and the driver (the bytes of a pause, whose times can no
        longer be known); returns the bytes discarded. Call it right before the readings start."""
        dropped = 0
        while dropped < max_bytes:
            data = self.port.read(4096)
            if not data:
                break
            dropped += len(data)
        self._parser.reset()
        self._backlog.clear()
        return dropped

    def check_streaming(self, timeout_ns: int) -> StreamCheck:
        """Wait up to timeout_ns for one good frame (the start-up check): FRAMES when one came; SILENT
        when no byte did (not wired, not powered, wrong port); NO_FRAMES when bytes came but none formed
        a frame (most often a baud rate that differs from the part's). A port error raises OSError."""
        end = self.clock.now_ns() + timeout_ns
        bytes0, frames0 = self.bytes_read, self._parser.frames
        while True:
            self._drain()
            if self._parser.frames > frames0:
                return StreamCheck.FRAMES
            now = self.clock.now_ns()
            if now >= end:
                return StreamCheck.NO_FRAMES if self.bytes_read > bytes0 else StreamCheck.SILENT
            self.clock.sleep_until_ns(min(now + self.config.poll_interval_ns, end))

    def close(self) -> None:
        self.port.close()


class StreamCheck(Enum):
    """What the start-up check saw on the port (`Tfmini.check_streaming`)."""

    FRAMES = "frames"
    SILENT = "silent"
    NO_FRAMES = "no frames"
