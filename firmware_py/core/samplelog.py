"""Crash-safe, append-only sample log: one record per LiDAR range.

The payload process on the drone writes it; the ground station reads it. The
format is built so that a power cut loses at most the last unfinished block, a
damaged block is skipped and counted (never fatal), and the reader never raises
on any bytes.

File format
-----------
A sequence of framed blocks, nothing else (no file header outside the blocks)::

    offset  size  field
    0       4     MAGIC = b"PSLB"
    4       1     kind: b"H" header, b"S" samples, b"E" end (other kinds: skipped, counted)
    5       4     payload length, uint32 little-endian, at most MAX_PAYLOAD (16 MiB)
    9       4     CRC32, uint32 little-endian: zlib.crc32(kind + length bytes + payload)
    13      n     payload

* The first block is the header: UTF-8 JSON object. The writer adds
  ``"format": "pilescan-samplelog"``, ``"format_version": 1`` and ``"record_dtype"``
  (``SAMPLE_DTYPE.descr`` as a JSON list of ``[name, typestr]`` pairs) to the
  caller's dict. Only the first valid header block is used.
* Sample blocks: payload is the raw little-endian bytes of ``SAMPLE_DTYPE``
  records (packed, itemsize 59). A length that is not a multiple of the
  itemsize makes the block corrupt.
* The end block: UTF-8 JSON object ``{"records": n}``, written by ``close()`` after the
  last samples and by nothing else. The writer also puts ``"end_record": true`` in the
  header: a log whose header says so and that has no end block was not closed (a power
  cut, a crash, a full card), whatever its blocks' state (``SampleLog.closed_cleanly``).
  A log of an older writer, without the key, cannot tell (None).
* Every block is flushed (and fsync'd) as a whole, so after a crash only the
  final block can be incomplete.

Reader accounting rules
-----------------------
A *candidate* is any occurrence of MAGIC; it is *framed* when its declared
length is <= MAX_PAYLOAD, fits in the data and its CRC matches. Scanning resumes
after a framed block, or at candidate + 1 after a failure. A *damaged region* is
a maximal run of bytes between framed blocks (or the data ends); its bytes are
counted in ``bytes_skipped``. An *expected boundary* is offset 0, the end of a
framed block, or the declared end of a counted corrupt candidate.

1. A failed candidate counts as one corrupt block only if it starts at an
   expected boundary (so MAGIC-like bytes inside a damaged payload are not
   counted again).
2. A damaged region that does not begin with a candidate (e.g. a flipped magic
   or leading garbage) counts as one corrupt block.
3. A candidate whose declared extent runs past the end of the data (including
   an incomplete 13-byte head) is the truncated final block
   (``blocks_truncated = 1``) if no framed block follows it; if one does follow,
   it counts as corrupt under rule 1. A trailing proper prefix of MAGIC at an
   expected boundary is also a truncated block.
4. A framed block whose content is unusable (header not a JSON object, sample
   payload not a whole number of records) counts as corrupt; its bytes count as
   skipped.

``blocks_corrupt`` is therefore a lower bound on the number of blocks lost to
damage; a length field damaged in the *final* block is indistinguishable from a
power cut and reads as truncated.

Format checks
-------------
The reader recovers what it can from any bytes; whether the records mean what this
version's SAMPLE_DTYPE says is a separate question, answered by
``SampleLog.format_problem`` from the header's ``format``, ``format_version`` and
``record_dtype`` (``require_supported_format`` raises it as `UnsupportedLogFormat`).
A header that states another format name, a version this reader does not know
(FORMAT_VERSION and below) or another record layout is refused by every program
that turns records into numbers: reading version 99's bytes as version 1's would
give numbers that look fine and mean nothing. A header without these keys (a
hand-built log) is read as the current layout. A path is read with a size limit
(``max_bytes``, default MAX_LOG_BYTES) and only when it is a regular file
(`firmware_py.core.safe_read`).
"""

from __future__ import annotations

import enum
import io
import json
import os
import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from firmware_py.core.safe_read import InputError, read_bounded

MAGIC = b"PSLB"
KIND_HEADER = b"H"
KIND_SAMPLES = b"S"
KIND_END = b"E"
END_HEADER_KEY = "end_record"
"""The header key by which a writer says it closes its log with an end block (module docstring)."""


def end_payload(records: int) -> bytes:
    """The end block's payload for a log of `records` records."""
    return json.dumps({"records": int(records)}).encode("utf-8")

MAX_PAYLOAD = 16 * 1024 * 1024
FORMAT_NAME = "pilescan-samplelog"
FORMAT_VERSION = 1
SUPPORTED_VERSIONS = (1,)
"""Format versions this reader understands."""
MAX_LOG_BYTES = 4 * 1024**3
"""Largest sample log read from a path: 4 GiB is 73 M records, 40 hours at the LIDAR-Lite's 500 Hz (a
multirotor flies under one hour per battery); the reader holds the file and its records in memory once each."""

_HEAD = struct.Struct("<4scII")  # magic, kind, payload length, crc32
HEAD_SIZE = _HEAD.size  # 13
END_BLOCK_MAX_BYTES = HEAD_SIZE + len(end_payload(2**64))
"""The most bytes `close()` adds (the end block): what a writer under a size cap keeps free for it."""

SAMPLE_DTYPE = np.dtype([
    ("t_s", "<f8"),         # companion clock time, s
    ("range_m", "<f4"),     # measured range, m (meaningless when NO_RETURN is set)
    ("servo_rad", "<f4"),   # servo angle gamma, rad (0 = straight down, + to the right/starboard)
    ("sweep_dir", "i1"),    # +1 / -1 servo sweep direction at this sample
    ("flags", "<u2"),       # SampleFlags
    ("x_m", "<f8"), ("y_m", "<f8"), ("z_m", "<f8"),   # vehicle position, local NED, m
    ("roll_rad", "<f4"), ("pitch_rad", "<f4"), ("yaw_rad", "<f4"),  # vehicle attitude, ZYX Euler, rad
    ("pose_age_s", "<f4"),  # age of the pose data used to tag this sample, s
])


class SampleFlags(enum.IntFlag):
    """Per-sample quality flags; any flag in EXCLUDE_FROM_CLOUD keeps a sample out of the cloud."""

    NONE = 0
    NO_RETURN = 1        # no valid echo (LIDAR-Lite reads 1 cm) or beyond max range
    STALE_POSE = 2       # pose too old to vouch for
    NO_POSE = 4          # no pose available at all
    SENSOR_ERROR = 8     # bus error / timeout on this measurement
    SERVO_UNCERTAIN = 16  # servo angle cannot be vouched for (stuck / slow servo)


UNPOSED = SampleFlags.STALE_POSE | SampleFlags.NO_POSE
"""A sample with either flag has no pose to vouch for: its position is zero or old."""

EXCLUDE_FROM_CLOUD = (
    SampleFlags.NO_RETURN
    | SampleFlags.STALE_POSE
    | SampleFlags.NO_POSE
    | SampleFlags.SENSOR_ERROR
    | SampleFlags.SERVO_UNCERTAIN
)

WRITER_HEADER_KEYS = ("format", "format_version", "record_dtype")
"""The header keys the writer adds itself and refuses from its caller (`SampleLogWriter`)."""


def rewritable_header(header: dict) -> dict:
    """A log's header without the keys its writer added: what a new writer may be given to write the same survey
    again (a copy, a merge, a header changed in one field)."""
    return {k: v for k, v in header.items() if k not in WRITER_HEADER_KEYS}


def new_records(n: int) -> np.ndarray:
    """Zeroed records, so callers fill fields by name and never forget one."""
    return np.zeros(n, dtype=SAMPLE_DTYPE)


def encode_block(kind: bytes, payload: bytes) -> bytes:
    """Frame one block; shared by the log writer and the live UDP stream."""
    if not isinstance(kind, bytes | bytearray) or len(kind) != 1:
        raise ValueError(f"block kind must be exactly one byte, got {kind!r}")
    payload = bytes(payload)
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"block payload of {len(payload)} bytes exceeds the {MAX_PAYLOAD} byte limit")
    length = struct.pack("<I", len(payload))
    crc = zlib.crc32(payload, zlib.crc32(bytes(kind) + length))
    return MAGIC + bytes(kind) + length + struct.pack("<I", crc) + payload


# --------------------------------------------------------------------------- writer


def _validated_header(header: Any) -> bytes:
    """Header payload bytes; rejected up front so a bad header never produces a half-written log."""
    if not isinstance(header, dict):
        raise ValueError(f"header must be a dict, got {type(header).__name__}: {header!r}")
    clash = [k for k in WRITER_HEADER_KEYS if k in header]
    if clash:
        raise ValueError(f"header keys {clash} are reserved for the writer")
    full = {**header, "format": FORMAT_NAME, "format_version": FORMAT_VERSION,
            "record_dtype": [list(pair) for pair in SAMPLE_DTYPE.descr]}
    full.setdefault(END_HEADER_KEY, True)  # a header copied from a log keeps its place: it says the same
    try:
        text = json.dumps(full, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"header is not JSON-serialisable ({exc}): {header!r}") from exc
    return text.encode("utf-8")


def _validated_block_size(records_per_block: Any) -> int:
    """records_per_block must give 1 .. MAX_PAYLOAD bytes of records per block."""
    limit = MAX_PAYLOAD // SAMPLE_DTYPE.itemsize
    ok_type = isinstance(records_per_block, int | np.integer) and not isinstance(records_per_block, bool)
    if not ok_type or not 1 <= records_per_block <= limit:
        raise ValueError(f"records_per_block must be an int in [1, {limit}], got {records_per_block!r}")
    return int(records_per_block)


def _as_records(records: Any) -> np.ndarray:
    """1-D SAMPLE_DTYPE view of the input; no silent casts, since a wrong layout is a caller bug."""
    if isinstance(records, np.void):
        records = np.asarray(records)
    if not isinstance(records, np.ndarray):
        raise TypeError(f"records must be a numpy array of SAMPLE_DTYPE, got {type(records).__name__}")
    if records.dtype != SAMPLE_DTYPE:
        raise TypeError(f"records must have dtype SAMPLE_DTYPE, got {records.dtype}")
    if records.ndim > 1:
        raise ValueError(f"records must be 1-D (or a single record), got shape {records.shape}")
    return records.reshape(-1)


class RecordBatcher:
    """Records gathered into fixed-size batches: `emit(batch)` gets each full one as it fills (and a
    partial one on `flush`). The batch is a view into a reused buffer: emit must consume it at once.
    The sample log's blocks and the live stream's datagrams are both batches."""

    def __init__(self, size: int, emit: Callable[[np.ndarray], None]) -> None:
        self._buf = new_records(size)
        self._fill = 0
        self._emit = emit

    @property
    def pending(self) -> int:
        return self._fill

    def add(self, recs: np.ndarray) -> None:
        """Add a 0-d record or a 1-D array of them (SAMPLE_DTYPE, unchecked: callers check)."""
        cap = len(self._buf)
        if recs.ndim == 0:  # one record at a time, the payload loop's case: fast path
            self._buf[self._fill] = recs
            self._fill += 1
            if self._fill == cap:
                self.flush()
            return
        i = 0
        while i < len(recs):
            take = min(cap - self._fill, len(recs) - i)
            self._buf[self._fill:self._fill + take] = recs[i:i + take]
            self._fill += take
            i += take
            if self._fill == cap:
                self.flush()

    def flush(self) -> None:
        if self._fill:
            n, self._fill = self._fill, 0
            self._emit(self._buf[:n])


class SampleLogWriter:
    """Append-only writer; each full block is flushed and fsync'd so a power cut costs <= one block.

    ``fsync=False`` skips every os.fsync (header included) for tests and non-critical logs.
    ``records_written`` counts records already in the file; ``records_pending`` those still buffered.
    ``opener(path, mode)`` opens the file (default ``open``): the simulator's disk-full fault uses it.
    """

    def __init__(self, path: str | os.PathLike[str], header: dict, records_per_block: int = 500,
                 fsync: bool = True, *, overwrite: bool = False,
                 opener: Callable[[str | os.PathLike[str], str], BinaryIO] = open) -> None:
        header_payload = _validated_header(header)
        self._batch = RecordBatcher(_validated_block_size(records_per_block), self._write_samples)
        self._written = 0
        self._fsync = bool(fsync)
        self._file: BinaryIO | None = opener(path, "wb" if overwrite else "xb")
        try:
            self._write_block(KIND_HEADER, header_payload)
        except BaseException:
            self._file.close()
            self._file = None
            raise

    @property
    def records_written(self) -> int:
        """Records already written to the file (buffered ones excluded)."""
        return self._written

    @property
    def records_pending(self) -> int:
        """Records buffered for the next block."""
        return self._batch.pending

    @property
    def closed(self) -> bool:
        return self._file is None

    def append(self, records: np.ndarray | np.void) -> None:
        """Buffer records, writing every block as soon as it fills."""
        if self._file is None:
            raise ValueError("append() on a closed SampleLogWriter")
        if type(records) is np.ndarray and records.ndim == 0 and records.dtype == SAMPLE_DTYPE:
            self._batch.add(records)  # the payload loop's one record a tick, checked cheaply
        else:
            self._batch.add(_as_records(records))

    def flush(self) -> None:
        """Write buffered records as a (shorter) block, making them crash-safe now."""
        if self._file is not None:
            self._batch.flush()

    def close(self) -> None:
        """Flush, write the end block (the log was closed, not cut short) and close; safe to call repeatedly. A
        failed flush (a full card) writes no end block: the log then reads as not closed."""
        if self._file is None:
            return
        try:
            self.flush()
            self._write_block(KIND_END, end_payload(self._written))
        finally:
            self._file.close()
            self._file = None

    def abandon(self) -> None:
        """Close without writing the buffered records: exactly what a power cut leaves (the blocks
        already written stay). For fault injection and tests."""
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> SampleLogWriter:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def _write_samples(self, batch: np.ndarray) -> None:
        self._write_block(KIND_SAMPLES, batch.tobytes())
        self._written += len(batch)

    def _write_block(self, kind: bytes, payload: bytes) -> None:
        """Whole block, then flush + fsync: the durability boundary is the block."""
        if self._file is None:
            raise ValueError("write on a closed SampleLogWriter")
        self._file.write(encode_block(kind, payload))
        self._file.flush()
        if self._fsync:
            os.fsync(self._file.fileno())


# --------------------------------------------------------------------------- reader


@dataclass(frozen=True, eq=False)  # eq=False: array fields make == ambiguous
class SampleLog:
    """What could be recovered from a log, plus how much could not."""

    header: dict | None
    samples: np.ndarray
    blocks_ok: int
    blocks_corrupt: int
    blocks_truncated: int
    bytes_skipped: int
    blocks_unknown: int = 0
    end: dict | None = None
    """The end block's record (`SampleLogWriter.close`), None when the log has none."""

    @property
    def closed_cleanly(self) -> bool | None:
        """Whether the writer closed the log: True with its end block, False without one when the header says the
        writer writes it (the payload stopped before closing: a power cut, a crash, a full card), None when the
        header does not say so (an older writer's log, or no header)."""
        if not isinstance(self.header, dict) or self.header.get(END_HEADER_KEY) is not True:
            return None
        return self.end is not None

    @property
    def format_problem(self) -> str | None:
        """Why the records cannot be read as this version's SAMPLE_DTYPE (None: they can, or no header)."""
        return header_format_problem(self.header)

    def require_supported_format(self, where: str) -> None:
        """Raise UnsupportedLogFormat (one line, naming `where`) when `format_problem` is set."""
        problem = self.format_problem
        if problem is not None:
            raise UnsupportedLogFormat(f"{where}: {problem}")

    @property
    def intact(self) -> bool:
        """True when nothing was lost (unknown block kinds are forward-compatible, not damage)."""
        return self.blocks_corrupt == 0 and self.blocks_truncated == 0


class UnsupportedLogFormat(ValueError):
    """The log states a format, version or record layout this reader does not support."""


def _layout_text(layout: Any) -> str:
    try:
        text = json.dumps(layout)
    except (TypeError, ValueError):
        text = repr(layout)
    return text if len(text) <= 80 else text[:77] + "..."


def header_format_problem(header: Any) -> str | None:
    """One line saying what the header's format keys state and what this reader supports, or None.

    Absent keys are taken as this version's (a hand-built header); present ones must match.
    """
    if not isinstance(header, dict):
        return None
    name = header.get("format", FORMAT_NAME)
    if name != FORMAT_NAME:
        return f"the log is of format {_layout_text(name)}, this reader supports {FORMAT_NAME!r}"
    version = header.get("format_version", FORMAT_VERSION)
    if isinstance(version, bool) or not isinstance(version, int) or version not in SUPPORTED_VERSIONS:
        supported = ", ".join(str(v) for v in SUPPORTED_VERSIONS)
        return (f"the log is {FORMAT_NAME} version {_layout_text(version)}, this reader supports version "
                f"{supported} (a newer pilescan wrote it?)")
    if "record_dtype" in header:
        want = [list(pair) for pair in SAMPLE_DTYPE.descr]
        if header["record_dtype"] != want:
            return (f"the log's records have layout {_layout_text(header['record_dtype'])}, this reader "
                    f"supports {_layout_text(want)}")
    return None


_FRAMED, _FAILED, _PAST_EOF = 0, 1, 2


class _Scanner:
    """One pass over the bytes; state lives here so each step stays a small method."""

    def __init__(self, data: bytes) -> None:
        self.data = data
        self.view = memoryview(data)
        self.n = len(data)
        self.header: dict | None = None
        self.chunks: list[memoryview] = []
        self.ok = self.corrupt = self.truncated = self.unknown = self.skipped = 0
        self.end: dict | None = None
        self._start_region(0)

    def _start_region(self, start: int) -> None:
        self.region_start = start
        self.expected = {start}
        self.pending_past_eof = False  # some candidate ran past EOF
        self.pending_expected = False  # ... and one of them sat on an expected boundary

    def run(self) -> SampleLog:
        pos = 0
        while pos < self.n:
            i = self.data.find(MAGIC, pos)
            if i < 0:
                break
            pos = self._candidate(i)
        self._end_region(self.n, at_eof=True)
        return self._result()

    def _candidate(self, i: int) -> int:
        """Classify the candidate at i; return where scanning resumes."""
        status, end = self._frame(i)
        if status == _FRAMED:
            self._end_region(i, at_eof=False)
            self._accept(i, end)
            self._start_region(end)
            return end
        at_expected = i in self.expected
        if status == _PAST_EOF:
            self.pending_past_eof = True
            self.pending_expected |= at_expected
        elif at_expected:
            self.corrupt += 1
            if end is not None:
                self.expected.add(end)
        return i + 1

    def _frame(self, i: int) -> tuple[int, int | None]:
        """(status, declared end) of the candidate block at i."""
        if self.n - i < HEAD_SIZE:
            return _PAST_EOF, None
        _, _, length, crc = _HEAD.unpack_from(self.data, i)
        if length > MAX_PAYLOAD:
            return _FAILED, None
        end = i + HEAD_SIZE + length
        if end > self.n:
            return _PAST_EOF, None
        actual = zlib.crc32(self.view[i + HEAD_SIZE:end], zlib.crc32(self.view[i + 4:i + 9]))
        return (_FRAMED if actual == crc else _FAILED), end

    def _end_region(self, stop: int, at_eof: bool) -> None:
        """Apply rules 2 and 3 to the damaged region [region_start, stop)."""
        start = self.region_start
        if stop <= start:
            return
        self.skipped += stop - start
        if at_eof and (self.pending_past_eof or self._magic_prefix_at_eof()):
            self.truncated = 1
        elif not at_eof and self.pending_expected:
            self.corrupt += 1
        if self.data[start:start + len(MAGIC)] != MAGIC and not (at_eof and self._magic_prefix_at_eof()):
            self.corrupt += 1

    def _magic_prefix_at_eof(self) -> bool:
        """A cut inside the 4 magic bytes of the final block."""
        return any(0 < self.n - e < len(MAGIC) and MAGIC.startswith(self.data[e:]) for e in self.expected)

    def _accept(self, i: int, end: int) -> None:
        """Use a framed block according to its kind (rule 4 for unusable content)."""
        kind = self.data[i + 4:i + 5]
        payload = self.view[i + HEAD_SIZE:end]
        if kind == KIND_SAMPLES:
            usable = len(payload) % SAMPLE_DTYPE.itemsize == 0
            if usable:
                self.chunks.append(payload)
        elif kind == KIND_HEADER:
            usable = self._take_header(payload)
        elif kind == KIND_END:  # not counted with the data blocks: it holds no data, only that the log was closed
            record = self._json_object(payload)
            if record is not None:
                self.end = record
                return
            usable = False
        else:
            self.unknown += 1
            return
        if usable:
            self.ok += 1
        else:
            self.corrupt += 1
            self.skipped += end - i

    @staticmethod
    def _json_object(payload: memoryview) -> dict | None:
        try:
            obj = json.loads(bytes(payload).decode("utf-8"))
        except (ValueError, RecursionError):
            return None
        return obj if isinstance(obj, dict) else None

    def _take_header(self, payload: memoryview) -> bool:
        """Decode a header block; only the first valid one is kept."""
        obj = self._json_object(payload)
        if obj is None:
            return False
        if self.header is None:
            self.header = obj
        return True

    def _result(self) -> SampleLog:
        parts = [np.frombuffer(c, dtype=SAMPLE_DTYPE) for c in self.chunks]
        samples = np.concatenate(parts) if parts else new_records(0)
        return SampleLog(self.header, samples, self.ok, self.corrupt, self.truncated,
                         self.skipped, self.unknown, self.end)


def _read_source(source: Any, max_bytes: int) -> bytes:
    """All bytes of a path (a regular file of at most max_bytes), bytes-like object or binary file object
    (at most max_bytes read from it)."""
    if isinstance(source, bytes):
        return source
    if isinstance(source, bytearray | memoryview):
        return bytes(source)
    if isinstance(source, str | os.PathLike):
        return read_bounded(Path(source), max_bytes, "sample log")
    read = getattr(source, "read", None)
    if read is None or isinstance(source, io.TextIOBase):
        kind = type(source).__name__
        raise TypeError(f"source must be a path, bytes-like or binary file object, got {kind}")
    data = read(max_bytes + 1)
    if not isinstance(data, bytes | bytearray | memoryview):
        raise TypeError(f"file object returned {type(data).__name__}, open it in binary mode")
    if len(data) > max_bytes:
        raise InputError(f"sample log stream is more than the {max_bytes:,} byte limit")
    return bytes(data)


def read_samplelog(source: str | os.PathLike[str] | bytes | bytearray | memoryview | BinaryIO, *,
                   max_bytes: int = MAX_LOG_BYTES) -> SampleLog:
    """Recover everything recoverable; never raises on content (OSError for unreadable paths, InputError
    for a path that is not a regular file or a source larger than max_bytes). Whether the records are of
    this version's layout is `SampleLog.format_problem`'s question."""
    return _Scanner(_read_source(source, max_bytes)).run()
