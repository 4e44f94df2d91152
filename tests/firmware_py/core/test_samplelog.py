"""Sample log: round trips, and the reader surviving truncation, bit rot and garbage without raising."""

from __future__ import annotations

import io
import json
import os
import struct
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given
from hypothesis import strategies as st

from firmware_py.core import samplelog as sl
from firmware_py.core.samplelog import (
    EXCLUDE_FROM_CLOUD,
    HEAD_SIZE,
    MAGIC,
    MAX_PAYLOAD,
    SAMPLE_DTYPE,
    SampleFlags,
    SampleLogWriter,
    encode_block,
    new_records,
    read_samplelog,
)
from tests.fuzz_budget import budget

HEADER = {"flight": "2024-05-01T10:00:00Z", "site": "quarry-7", "servo_hz": 2.5}
FAST = budget(200, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def make_records(n: int, seed: int = 0) -> np.ndarray:
    """Records with every field populated, so a misplaced byte cannot go unnoticed."""
    rng = np.random.default_rng(seed)
    r = new_records(n)
    r["t_s"] = 1000.0 + np.arange(n) * 0.002
    floats = ("range_m", "servo_rad", "x_m", "y_m", "z_m", "roll_rad", "pitch_rad", "yaw_rad", "pose_age_s")
    for name in floats:
        r[name] = rng.uniform(-50.0, 50.0, n)
    r["sweep_dir"] = rng.choice([-1, 1], n)
    r["flags"] = rng.integers(0, 32, n)
    return r


def write_log(path: Path, records: np.ndarray, records_per_block: int, end: bool = True) -> bytes:
    """The log's bytes; end=False: as a power cut after the last block leaves it (no end record)."""
    w = SampleLogWriter(path, HEADER, records_per_block=records_per_block, fsync=False)
    w.append(records)
    if end:
        w.close()
    else:
        w.flush()
        w.abandon()
    return path.read_bytes()


def block_spans(data: bytes) -> list[tuple[int, int]]:
    """(start, end) of each block of an undamaged log, header first."""
    spans, pos = [], 0
    while pos < len(data):
        (length,) = struct.unpack_from("<I", data, pos + 5)
        spans.append((pos, pos + HEAD_SIZE + length))
        pos += HEAD_SIZE + length
    return spans


def same_records(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == SAMPLE_DTYPE and b.dtype == SAMPLE_DTYPE and a.tobytes() == b.tobytes()


# Five sample blocks of seven records each; built once (hypothesis cannot use tmp_path).
N_BLOCKS, PER_BLOCK = 5, 7


@pytest.fixture(scope="module")
def log5(tmp_path_factory: pytest.TempPathFactory) -> tuple[bytes, np.ndarray, list[tuple[int, int]]]:
    records = make_records(N_BLOCKS * PER_BLOCK, seed=5)
    data = write_log(tmp_path_factory.mktemp("log5") / "five.pslog", records, PER_BLOCK, end=False)
    spans = block_spans(data)
    if len(spans) != N_BLOCKS + 1:
        raise RuntimeError(f"fixture expected {N_BLOCKS + 1} blocks, got {len(spans)}")
    return data, records, spans


def records_of_blocks(records: np.ndarray, block_indices: list[int]) -> np.ndarray:
    """Records of the given sample blocks (1-based block index; 0 is the header)."""
    parts = [records[(k - 1) * PER_BLOCK:k * PER_BLOCK] for k in block_indices if k >= 1]
    return np.concatenate(parts) if parts else new_records(0)


# --------------------------------------------------------------------------- round trip


def test_round_trip_through_file_keeps_header_and_every_record(tmp_path: Path) -> None:
    records = make_records(1234, seed=1)
    path = tmp_path / "flight.pslog"
    with SampleLogWriter(path, HEADER, records_per_block=100) as w:
        w.append(records[:600])
        w.append(records[600:])
        assert w.records_written == 1200
        assert w.records_pending == 34
    assert w.records_written == 1234
    log = read_samplelog(path)
    assert {k: log.header[k] for k in HEADER} == HEADER
    assert log.header["format"] == "pilescan-samplelog"
    assert log.header["format_version"] == 1
    assert np.dtype([tuple(p) for p in log.header["record_dtype"]]) == SAMPLE_DTYPE
    assert same_records(log.samples, records)
    assert (log.blocks_ok, log.blocks_corrupt, log.blocks_truncated, log.bytes_skipped) == (1 + 13, 0, 0, 0)
    assert log.intact


def test_round_trip_through_bytes_bytearray_memoryview_and_file_object(tmp_path: Path) -> None:
    records = make_records(50, seed=2)
    data = write_log(tmp_path / "a.pslog", records, 8)
    for source in (data, bytearray(data), memoryview(data), str(tmp_path / "a.pslog")):
        log = read_samplelog(source)
        assert same_records(log.samples, records) and log.intact
    with open(tmp_path / "a.pslog", "rb") as f:
        assert same_records(read_samplelog(f).samples, records)
    assert same_records(read_samplelog(io.BytesIO(data)).samples, records)


def test_read_samples_are_writable_copies() -> None:
    log = read_samplelog(encode_block(b"S", make_records(3).tobytes()))
    log.samples["range_m"] = 1.0
    assert log.samples.flags.writeable


def test_flush_writes_partial_block_and_close_is_idempotent(tmp_path: Path) -> None:
    path = tmp_path / "p.pslog"
    records = make_records(10, seed=3)
    w = SampleLogWriter(path, HEADER, records_per_block=100)
    w.append(records)
    assert w.records_written == 0 and read_samplelog(path).samples.size == 0
    w.flush()
    assert w.records_written == 10
    log = read_samplelog(path)
    assert same_records(log.samples, records) and log.blocks_ok == 2
    w.flush()  # nothing pending: no empty block
    w.close()
    w.close()
    assert w.closed and read_samplelog(path).blocks_ok == 2
    with pytest.raises(ValueError, match="closed"):
        w.append(records)


def test_single_void_record_is_accepted(tmp_path: Path) -> None:
    records = make_records(3, seed=4)
    with SampleLogWriter(tmp_path / "v.pslog", HEADER, records_per_block=2) as w:
        for rec in records:
            w.append(rec)
    assert same_records(read_samplelog(tmp_path / "v.pslog").samples, records)


def test_empty_input_and_header_only_log_are_intact_and_empty(tmp_path: Path) -> None:
    empty = read_samplelog(b"")
    assert empty.header is None and empty.samples.dtype == SAMPLE_DTYPE and empty.samples.size == 0
    assert empty.intact
    with SampleLogWriter(tmp_path / "h.pslog", HEADER):
        pass
    log = read_samplelog(tmp_path / "h.pslog")
    assert log.header is not None and log.samples.size == 0 and log.blocks_ok == 1 and log.intact


def test_exclude_from_cloud_covers_every_quality_flag() -> None:
    every = SampleFlags(0)
    for flag in SampleFlags:
        every |= flag
    assert every == EXCLUDE_FROM_CLOUD


# --------------------------------------------------------------------------- truncation


def test_truncation_anywhere_in_last_two_blocks_returns_every_complete_block(log5) -> None:
    data, records, spans = log5
    ends = {end for _, end in spans}
    for cut in range(spans[-2][0], len(data) + 1):
        log = read_samplelog(data[:cut])
        complete = [k for k, (_, end) in enumerate(spans) if end <= cut]
        assert log.samples.size == PER_BLOCK * (len(complete) - 1), cut
        assert same_records(log.samples, records_of_blocks(records, complete)), cut
        assert log.blocks_corrupt == 0, cut
        assert log.blocks_truncated == (0 if cut in ends else 1), cut
        assert log.bytes_skipped == cut - max(e for e in ends if e <= cut), cut
        assert log.header is not None


def test_length_damage_in_final_block_reads_as_power_cut(log5) -> None:
    data, records, spans = log5
    start = spans[-1][0]
    damaged = bytearray(data)
    damaged[start + 7] ^= 0xFF  # declared length now runs past the end of the file
    log = read_samplelog(bytes(damaged))
    assert (log.blocks_corrupt, log.blocks_truncated) == (0, 1)
    assert same_records(log.samples, records[:(N_BLOCKS - 1) * PER_BLOCK])


# --------------------------------------------------------------------------- bit rot

FLIP_OFFSETS = {"magic": 0, "kind": 4, "length_lsb": 5, "length_msb": 8, "crc": 9,
                "payload_first": HEAD_SIZE, "payload_mid": HEAD_SIZE + 200, "payload_last": -1}


@pytest.mark.parametrize("where", FLIP_OFFSETS)
@pytest.mark.parametrize("block", range(1, N_BLOCKS + 1))
def test_flipped_byte_loses_exactly_that_block(log5, block: int, where: str) -> None:
    data, records, spans = log5
    start, end = spans[block]
    offset = FLIP_OFFSETS[where]
    damaged = bytearray(data)
    damaged[end + offset if offset < 0 else start + offset] ^= 0xFF
    log = read_samplelog(bytes(damaged))
    survivors = [k for k in range(1, N_BLOCKS + 1) if k != block]
    assert same_records(log.samples, records_of_blocks(records, survivors))
    assert log.blocks_corrupt >= 1
    if where in ("crc", "payload_first", "payload_mid", "payload_last"):
        assert log.blocks_corrupt == 1
    assert log.blocks_truncated == 0 and log.blocks_ok == N_BLOCKS and not log.intact
    assert log.bytes_skipped == end - start


@pytest.mark.parametrize("block", range(1, N_BLOCKS))
def test_length_running_past_eof_before_a_valid_block_is_corrupt_not_truncated(log5, block: int) -> None:
    data, records, spans = log5
    damaged = bytearray(data)
    damaged[spans[block][0] + 7] ^= 0xFF
    log = read_samplelog(bytes(damaged))
    assert (log.blocks_corrupt, log.blocks_truncated) == (1, 0)
    survivors = [k for k in range(1, N_BLOCKS + 1) if k != block]
    assert same_records(log.samples, records_of_blocks(records, survivors))


def test_oversized_declared_length_is_corrupt_and_reading_continues() -> None:
    recs = make_records(4, seed=6)
    bogus = MAGIC + b"S" + struct.pack("<II", MAX_PAYLOAD + 1, 0) + b"\x00" * 20
    log = read_samplelog(bogus + encode_block(b"S", recs.tobytes()))
    assert (log.blocks_corrupt, log.blocks_ok) == (1, 1)
    assert same_records(log.samples, recs)


def test_sample_payload_not_a_whole_number_of_records_is_corrupt() -> None:
    recs = make_records(2, seed=7)
    data = encode_block(b"S", recs.tobytes()[:-1]) + encode_block(b"S", recs.tobytes())
    log = read_samplelog(data)
    assert (log.blocks_corrupt, log.blocks_ok) == (1, 1)
    assert same_records(log.samples, recs)


def test_unknown_block_kind_is_skipped_and_counted_without_breaking_intact() -> None:
    recs = make_records(3, seed=8)
    data = encode_block(b"H", b"{}") + encode_block(b"X", b"future") + encode_block(b"S", recs.tobytes())
    log = read_samplelog(data)
    assert (log.blocks_unknown, log.blocks_ok, log.bytes_skipped) == (1, 2, 0)
    assert log.intact and same_records(log.samples, recs)


def test_leading_garbage_counts_one_corrupt_region() -> None:
    recs = make_records(3, seed=9)
    log = read_samplelog(b"garbage!" + encode_block(b"S", recs.tobytes()))
    assert (log.blocks_corrupt, log.bytes_skipped) == (1, 8)
    assert same_records(log.samples, recs)


# --------------------------------------------------------------------------- header damage


def test_corrupt_header_gives_none_but_samples_survive(log5) -> None:
    data, records, _ = log5
    damaged = bytearray(data)
    damaged[HEAD_SIZE + 2] ^= 0xFF
    log = read_samplelog(bytes(damaged))
    assert log.header is None and log.blocks_corrupt == 1
    assert same_records(log.samples, records)


@pytest.mark.parametrize("payload", [b"not json", b"[1, 2]", b"\xff\xfe", b"[" * 100_000])
def test_header_with_valid_crc_but_not_a_json_object_is_corrupt(payload: bytes) -> None:
    recs = make_records(2, seed=10)
    log = read_samplelog(encode_block(b"H", payload) + encode_block(b"S", recs.tobytes()))
    assert log.header is None and (log.blocks_corrupt, log.blocks_ok) == (1, 1)
    assert same_records(log.samples, recs)


def test_only_first_valid_header_is_used() -> None:
    data = encode_block(b"H", b'{"n": 1}') + encode_block(b"H", b'{"n": 2}')
    log = read_samplelog(data)
    assert log.header == {"n": 1} and log.blocks_ok == 2


# --------------------------------------------------------------------------- hypothesis

_block_ish = st.one_of(
    st.binary(max_size=64),
    st.just(MAGIC),
    st.builds(encode_block, st.sampled_from([b"H", b"S", b"?"]), st.binary(max_size=120)),
    st.builds(lambda n: encode_block(b"S", make_records(n).tobytes()), st.integers(0, 3)),
)


def check_well_formed(log: sl.SampleLog, size: int) -> None:
    assert log.samples.dtype == SAMPLE_DTYPE and log.samples.ndim == 1
    assert log.header is None or isinstance(log.header, dict)
    assert min(log.blocks_ok, log.blocks_corrupt, log.bytes_skipped, log.blocks_unknown) >= 0
    assert log.blocks_truncated in (0, 1) and log.bytes_skipped <= size


@FAST
@given(st.binary(max_size=4096))
def test_arbitrary_bytes_never_raise(data: bytes) -> None:
    check_well_formed(read_samplelog(data), len(data))


@FAST
@given(st.lists(_block_ish, max_size=12))
def test_arbitrary_block_like_fragments_never_raise(parts: list[bytes]) -> None:
    data = b"".join(parts)
    check_well_formed(read_samplelog(data), len(data))


def damaged_blocks(data: bytes, spans: list[tuple[int, int]], pos: int, garbage: bytes,
                   overwrite: bool) -> list[int]:
    """Blocks touched by the damage whose exact bytes no longer appear anywhere in the result."""
    if overwrite:
        n = min(len(data), pos + len(garbage))
        overlaps = [(k, max(s, pos), min(e, n)) for k, (s, e) in enumerate(spans)]
        touched = [k for k, lo, hi in overlaps if lo < hi and data[lo:hi] != garbage[lo - pos:hi - pos]]
        damaged = data[:pos] + garbage + data[pos + len(garbage):]
    else:
        touched = [k for k, (s, e) in enumerate(spans) if s < pos < e]
        damaged = data[:pos] + garbage + data[pos:]
    return [k for k in touched if data[spans[k][0]:spans[k][1]] not in damaged]


@FAST
@given(pos=st.integers(0, 10**6), garbage=st.binary(min_size=1, max_size=64), overwrite=st.booleans())
def test_damage_anywhere_spares_blocks_outside_it(log5, pos: int, garbage: bytes, overwrite: bool) -> None:
    data, records, spans = log5
    pos %= len(data) + 1
    tail = data[pos + len(garbage):] if overwrite else data[pos:]
    damaged = data[:pos] + garbage + tail
    lost = damaged_blocks(data, spans, pos, garbage, overwrite)
    log = read_samplelog(damaged)
    check_well_formed(log, len(damaged))
    survivors = [k for k in range(1, N_BLOCKS + 1) if k not in lost]
    assert same_records(log.samples, records_of_blocks(records, survivors))
    assert (log.header is None) == (0 in lost)
    if damaged != data:
        assert not log.intact


_json_scalars = st.one_of(st.none(), st.booleans(), st.integers(-(2**70), 2**70),
                         st.floats(allow_nan=False, allow_infinity=False), st.text(max_size=20))
_json = st.recursive(_json_scalars, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                            st.dictionaries(st.text(max_size=8), inner, max_size=4)),
                     max_leaves=20)
_user_headers = st.dictionaries(st.text(max_size=12).filter(lambda k: k not in sl.WRITER_HEADER_KEYS), _json,
                                max_size=6)


@pytest.fixture(scope="module")
def scratch(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("fuzz") / "h.pslog"


@FAST
@given(header=_user_headers, n=st.integers(0, 3))
def test_any_json_header_round_trips_through_writer_and_reader(scratch, header: dict, n: int) -> None:
    recs = make_records(n, seed=n)
    with SampleLogWriter(scratch, header, records_per_block=2, fsync=False, overwrite=True) as w:
        w.append(recs)
    log = read_samplelog(scratch)
    assert log.intact and same_records(log.samples, recs)
    # the writer's promise of an end record, unless the header made it already (a header copied from a log)
    assert sl.rewritable_header(log.header) == {sl.END_HEADER_KEY: True,
                                                                                         **header}
    assert log.header["format"] == sl.FORMAT_NAME


@FAST
@given(payload=st.one_of(_json.map(json.dumps), st.recursive(_json_scalars | st.floats(), st.lists).map(json.dumps),
                         st.text(max_size=200), st.binary(max_size=200).map(lambda b: b.decode("latin-1"))),
       encoding=st.sampled_from(["utf-8", "utf-16", "latin-1"]))
def test_header_block_with_any_payload_gives_its_json_object_or_none(payload: str, encoding: str) -> None:
    """Any header content in a valid block: the header is the JSON object it holds, or None (block corrupt)."""
    raw = payload.encode(encoding, errors="replace")
    recs = make_records(2, seed=11)
    log = read_samplelog(encode_block(b"H", raw) + encode_block(b"S", recs.tobytes()))
    try:
        expected = json.loads(raw.decode("utf-8"))
    except (ValueError, RecursionError):
        expected = None
    if not isinstance(expected, dict):
        expected = None
    assert log.header == expected or (expected is not None and json.dumps(log.header) == json.dumps(expected))
    assert (log.blocks_ok, log.blocks_corrupt) == ((2, 0) if expected is not None else (1, 1))
    assert same_records(log.samples, recs)


_no_magic = st.binary(max_size=64).map(lambda b: b.replace(MAGIC[:1], b"Q"))
"""Block bodies holding no MAGIC, nor a prefix of it (which would be a block boundary of its own)."""


@FAST
@given(length=st.one_of(st.integers(0, 2**32 - 1), st.sampled_from([MAX_PAYLOAD, MAX_PAYLOAD + 1, 2**32 - 1])),
       kind=st.sampled_from([b"H", b"S", b"?"]), crc=st.integers(0, 2**32 - 1), body=_no_magic,
       n_after=st.integers(1, 3))
def test_any_declared_length_costs_only_its_own_block(length: int, kind: bytes, crc: int, body: bytes,
                                                      n_after: int) -> None:
    """A block head claiming any length (up to 4 GiB), then good blocks: only the liar is lost, counted."""
    recs = make_records(3 * n_after, seed=length % 1000)
    good = b"".join(encode_block(b"S", recs[3 * k:3 * k + 3].tobytes()) for k in range(n_after))
    liar = MAGIC + kind + struct.pack("<II", length, crc) + body
    log = read_samplelog(encode_block(b"H", b'{"n": 1}') + liar + good)
    assert log.header == {"n": 1} and same_records(log.samples, recs)
    assert log.blocks_ok == 1 + n_after and log.blocks_corrupt >= 1 and log.blocks_truncated == 0
    assert log.bytes_skipped == len(liar)


@FAST
@given(length=st.integers(0, 2**32 - 1), body=_no_magic)
def test_any_declared_length_in_the_final_block_reads_as_truncated_or_corrupt(length: int, body: bytes) -> None:
    recs = make_records(3, seed=12)
    good = encode_block(b"H", b"{}") + encode_block(b"S", recs.tobytes())
    liar = MAGIC + b"S" + struct.pack("<II", length, 0) + body
    log = read_samplelog(good + liar)
    assert same_records(log.samples, recs) and log.bytes_skipped == len(liar)
    past_eof = length <= MAX_PAYLOAD and len(body) < length
    assert (log.blocks_truncated, log.blocks_corrupt) == ((1, 0) if past_eof else (0, 1))


# --------------------------------------------------------------------------- writer validation


def test_writer_rejects_wrong_record_types(tmp_path: Path) -> None:
    with SampleLogWriter(tmp_path / "w.pslog", HEADER, fsync=False) as w:
        with pytest.raises(TypeError, match="dtype"):
            w.append(np.zeros(3))
        with pytest.raises(TypeError, match="dtype"):
            w.append(np.zeros(3, dtype=[("t_s", "<f8"), ("range_m", "<f4")]))
        with pytest.raises(TypeError, match="dtype"):
            w.append(new_records(3).astype(SAMPLE_DTYPE.newbyteorder(">")))
        with pytest.raises(TypeError, match="numpy array"):
            w.append([1, 2, 3])
        with pytest.raises(ValueError, match="1-D"):
            w.append(new_records(4).reshape(2, 2))
        assert w.records_pending == 0


@pytest.mark.parametrize("bad", [0, -1, 1.5, "10", True, MAX_PAYLOAD])
def test_writer_rejects_bad_records_per_block(tmp_path: Path, bad: object) -> None:
    with pytest.raises(ValueError, match="records_per_block"):
        SampleLogWriter(tmp_path / "r.pslog", HEADER, records_per_block=bad)
    assert not (tmp_path / "r.pslog").exists()


@pytest.mark.parametrize("bad", [None, [("a", 1)], "header", {"x": object()}, {"x": float("nan")},
                                 {"format": "mine"}])
def test_writer_rejects_bad_header(tmp_path: Path, bad: object) -> None:
    with pytest.raises(ValueError, match="header"):
        SampleLogWriter(tmp_path / "h.pslog", bad)
    assert not (tmp_path / "h.pslog").exists()


def test_writer_refuses_to_overwrite_unless_asked(tmp_path: Path) -> None:
    path = tmp_path / "exists.pslog"
    path.write_bytes(b"precious")
    with pytest.raises(FileExistsError):
        SampleLogWriter(path, HEADER)
    assert path.read_bytes() == b"precious"
    with SampleLogWriter(path, HEADER, overwrite=True, fsync=False) as w:
        w.append(make_records(2))
    assert read_samplelog(path).samples.size == 2


def test_encode_block_rejects_bad_kind_and_oversized_payload() -> None:
    with pytest.raises(ValueError, match="kind"):
        encode_block(b"SS", b"")
    with pytest.raises(ValueError, match="exceeds"):
        encode_block(b"S", bytes(MAX_PAYLOAD + 1))


def test_reader_rejects_text_file_objects_and_unknown_types(tmp_path: Path) -> None:
    with pytest.raises(TypeError):
        read_samplelog(io.StringIO("PSLB"))
    with pytest.raises(TypeError):
        read_samplelog(12345)
    with pytest.raises(FileNotFoundError):
        read_samplelog(tmp_path / "missing.pslog")


# --------------------------------------------------------------------------- durability and speed


def test_fsync_once_per_block_plus_header(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[int] = []
    monkeypatch.setattr(os, "fsync", calls.append)
    with SampleLogWriter(tmp_path / "f.pslog", HEADER, records_per_block=4) as w:
        assert len(calls) == 1  # header is durable before any sample arrives
        w.append(make_records(10))
        assert len(calls) == 1 + 2
        w.append(make_records(1))
        assert len(calls) == 3
    assert len(calls) == 5  # close wrote the 3-record partial block and the end record
    calls.clear()
    with SampleLogWriter(tmp_path / "g.pslog", HEADER, records_per_block=4, fsync=False) as w:
        w.append(make_records(10))
    assert calls == []


def test_header_json_is_plain_utf8_object(tmp_path: Path) -> None:
    path = tmp_path / "j.pslog"
    with SampleLogWriter(path, {"pilot": "Zoë"}, fsync=False):
        pass
    data = path.read_bytes()
    assert data[:5] == MAGIC + b"H"
    (length,) = struct.unpack_from("<I", data, 5)
    assert json.loads(data[HEAD_SIZE:HEAD_SIZE + length].decode("utf-8"))["pilot"] == "Zoë"


def test_that_a_100k_record_log_reads_back_whole(tmp_path: Path) -> None:
    # Speed is measured in tools/bench_ground.py, never asserted in a test.
    recs = make_records(200 * 500)
    data = write_log(tmp_path / "big.pslog", recs, 500)
    log = read_samplelog(data)
    assert log.blocks_ok == 201 and log.samples.size == 100_000
    assert np.array_equal(log.samples, recs)


class _FullDisk:
    """A file that takes `room` more bytes, writes what fits of the next write, then fails ENOSPC."""

    def __init__(self, f, room):
        self.f, self.room = f, room

    def write(self, data):
        if len(data) > self.room:
            self.f.write(data[: self.room])  # a real full disk can take part of a write
            self.room = 0
            raise OSError(28, "No space left on device")
        self.room -= len(data)
        return self.f.write(data)

    def __getattr__(self, name):
        return getattr(self.f, name)


def test_that_a_full_disk_stops_the_writer_loudly_and_keeps_every_whole_block(tmp_path):
    path = tmp_path / "full.pslog"
    w = SampleLogWriter(path, {"test": True}, records_per_block=100, fsync=False)
    w._file = _FullDisk(w._file, room=3 * (100 * SAMPLE_DTYPE.itemsize + 64) + 50)
    recs = new_records(1000)
    recs["t_s"] = np.arange(1000)
    with pytest.raises(OSError, match="No space"):
        w.append(recs)
    w.abandon()
    log = read_samplelog(path)
    assert len(log.samples) == 300 and np.array_equal(log.samples["t_s"], np.arange(300))
    assert log.blocks_corrupt == 0 and log.blocks_truncated == 1  # the block that did not fit


def test_that_a_closed_log_ends_with_its_end_record_and_reads_as_closed(tmp_path):
    path = tmp_path / "closed.pslog"
    with SampleLogWriter(path, HEADER, records_per_block=4, fsync=False) as w:
        w.append(make_records(10))
    log = read_samplelog(path)
    assert log.closed_cleanly is True and log.end == {"records": 10}
    assert log.header[sl.END_HEADER_KEY] is True and log.intact
    assert (log.blocks_ok, log.blocks_unknown) == (1 + 3, 0)  # the end block is no data block
    assert path.read_bytes().endswith(encode_block(sl.KIND_END, b'{"records": 10}'))


def test_that_a_log_never_closed_reads_as_cut_short_and_an_older_writers_as_unknown(tmp_path):
    path = tmp_path / "cut.pslog"
    w = SampleLogWriter(path, HEADER, records_per_block=4, fsync=False)
    w.append(make_records(10))
    w.abandon()  # a power cut: the whole blocks stay, no end record
    log = read_samplelog(path)
    assert log.closed_cleanly is False and log.end is None and log.intact and len(log.samples) == 8
    older = encode_block(sl.KIND_HEADER, json.dumps(HEADER).encode()) + encode_block(sl.KIND_SAMPLES,
                                                                                    make_records(3).tobytes())
    assert read_samplelog(older).closed_cleanly is None  # no promise of an end record in its header
    bad_end = older + encode_block(sl.KIND_END, b"[1, 2]")
    assert read_samplelog(bad_end).blocks_corrupt == 1 and read_samplelog(bad_end).end is None


def test_that_a_failed_last_flush_leaves_no_end_record(tmp_path):
    """A full card: the close fails on the buffered records and the log reads as not closed."""
    class Full(io.BytesIO):
        def __init__(self):
            super().__init__()
            self.full = False

        def write(self, b):
            if self.full:
                raise OSError(28, "No space left on device")
            return super().write(b)

        def close(self):
            self.saved = self.getvalue()
            super().close()

    f = Full()
    w = SampleLogWriter(tmp_path / "x", HEADER, records_per_block=4, fsync=False, opener=lambda p, m: f)
    w.append(make_records(6))
    f.full = True
    with pytest.raises(OSError):
        w.close()
    log = read_samplelog(f.saved)
    assert w.closed and log.closed_cleanly is False and len(log.samples) == 4
