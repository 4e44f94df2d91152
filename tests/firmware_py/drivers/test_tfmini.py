"""The TFMini-family driver: frames, what each model's codes mean, stamping, faults (no simulator)."""

import pytest
from hypothesis import given
from hypothesis import strategies as st

from firmware_py.drivers.reading import ReadStatus
from firmware_py.drivers.tfmini import (
    FRAME_LEN,
    Frame,
    FrameParser,
    Tfmini,
    TfminiConfig,
    TfminiModel,
    checksum,
    classify,
    encode_frame,
)
from firmware_py.hal.clock import SimClock

S = TfminiModel.TFMINI_S.value
MINI = TfminiModel.TFMINI.value


def test_that_a_frame_is_header_values_little_endian_and_the_low_byte_of_the_sum():
    f = encode_frame(523, 3000, 2400)
    assert f[:2] == b"\x59\x59" and len(f) == FRAME_LEN
    assert (f[2] | f[3] << 8, f[4] | f[5] << 8, f[6] | f[7] << 8) == (523, 3000, 2400)
    assert f[8] == sum(f[:8]) % 256 == checksum(f)


def test_that_the_parser_resynchronises_after_garbage_and_a_bad_checksum():
    good = encode_frame(420, 900)
    bad = good[:8] + bytes(((good[8] + 1) & 0xFF,))
    p = FrameParser()
    got = p.feed(b"\x00\x13\x59" + bad + good + b"\xff" + good)
    assert [fr.dist_raw for fr, _ in got] == [420, 420]
    # Two failed checksums: the stray 0x59 makes a misaligned header, then the corrupt frame itself.
    assert p.bad_checksums == 2 and p.frames == 2 and p.skipped_bytes == 2 + 1 + 1 + FRAME_LEN


def test_that_a_frame_split_across_reads_is_assembled_and_indexed_in_the_read_that_completes_it():
    f = encode_frame(1234, 500)
    p = FrameParser()
    assert p.feed(f[:5]) == []
    (frame, last), = p.feed(f[5:] + b"\x59")
    assert frame.dist_raw == 1234 and last == FRAME_LEN - 5 - 1


@given(st.binary(max_size=400))
def test_that_any_bytes_never_raise_and_never_grow_the_buffer(data):
    p = FrameParser()
    for i in range(0, len(data), 37):
        p.feed(data[i:i + 37])
    assert len(p._buf) < FRAME_LEN


@pytest.mark.parametrize(("dist", "strength", "model", "expected"), [
    (523, 3000, S, 5.23),
    (-1, 60, S, None),  # weak echo: the S reports -1
    (-2, 0xFFFF, S, None),  # saturated signal
    (-4, 800, S, None),  # ambient light saturated
    (523, 80, S, None),  # a distance with a strength under 100 is not trusted either
    (5, 3000, S, None),  # 5 cm: under the 0.1 m minimum
    (1250, 3000, S, None),  # beyond the 12 m rating
    (0xFFFF, 10, MINI, None),  # the TFmini's weak code
    (1200, 300, MINI, None),  # its "beyond 12 m" value (ArduPilot: the model maximum is out of range)
    (523, 2500, MINI, None),  # strength above its 2000 reliable ceiling
    (523, 300, MINI, 5.23),
])
def test_that_each_models_codes_mean_what_its_manual_says(dist, strength, model, expected):
    range_m, status = classify(Frame.from_bytes(encode_frame(dist, strength)), model)
    assert range_m == expected
    assert status == (ReadStatus.OK if expected is not None else ReadStatus.NO_RETURN)


class ScriptedPort:
    """A serial port that delivers scripted chunks at scripted times on a SimClock."""

    def __init__(self, clock, chunks):
        self.clock, self.chunks, self.closed = clock, sorted(chunks), False

    def read(self, n):
        out = b""
        while self.chunks and self.chunks[0][0] <= self.clock.now_ns():
            out += self.chunks.pop(0)[1]
        return out

    def close(self):
        self.closed = True


BYTE_NS = round(10 * 1e9 / 115_200)


def test_that_a_reading_is_stamped_at_its_frames_first_byte_to_within_one_poll():
    clock = SimClock()
    # The frame's last byte arrives at 5 ms: its first started 9 byte times (0.78 ms) before.
    port = ScriptedPort(clock, [(5_000_000, encode_frame(777, 2000))])
    lidar = Tfmini(port, clock, TfminiConfig(poll_interval_ns=100_000))
    r = lidar.read()
    assert r.status == ReadStatus.OK and r.range_m == 7.77
    true_first_byte = 5_000_000 - (FRAME_LEN - 1) * BYTE_NS
    assert true_first_byte <= r.t_ns <= true_first_byte + 100_000


def test_that_a_backlog_is_read_in_order_each_frame_a_period_apart():
    clock = SimClock()
    frames = b"".join(encode_frame(100 + i, 2000) for i in range(3))
    port = ScriptedPort(clock, [(0, frames)])
    lidar = Tfmini(port, clock)
    got = [lidar.read() for _ in range(3)]
    assert [r.range_m for r in got] == [1.0, 1.01, 1.02]
    assert got[1].t_ns - got[0].t_ns == got[2].t_ns - got[1].t_ns == 10_000_000


def test_that_a_silent_port_times_out_after_three_frame_periods_without_hanging():
    clock = SimClock()
    lidar = Tfmini(ScriptedPort(clock, []), clock)
    r = lidar.read()
    assert r.status == ReadStatus.TIMEOUT and r.range_m is None
    assert clock.now_ns() == 30_000_000
    assert lidar.counters().timeouts == 1 and lidar.counters().sensor_errors == 1


def test_that_a_port_error_is_a_bus_error_reading_not_an_exception():
    class Unplugged:
        def read(self, n):
            raise OSError(5, "device reports readiness to read but returned no data (device disconnected?)")

        def close(self):
            pass

    clock = SimClock()
    lidar = Tfmini(Unplugged(), clock)
    r = lidar.read()
    assert r.status == ReadStatus.BUS_ERROR and "disconnected" in str(lidar.last_error)


def test_that_a_backlog_longer_than_the_limit_drops_the_oldest_and_counts_them():
    clock = SimClock()
    port = ScriptedPort(clock, [(0, b"".join(encode_frame(100 + i, 2000) for i in range(10)))])
    lidar = Tfmini(port, clock, TfminiConfig(max_backlog=4))
    assert lidar.read().range_m == 1.06
    assert lidar.counters().dropped_backlog == 6


@pytest.mark.parametrize("bad", [
    {"baud": 115201}, {"frame_rate_hz": 0}, {"frame_rate_hz": 1000, "baud": 9600}, {"poll_interval_ns": 0},
    {"timeout_ns": -5}, {"max_backlog": 0}, {"model": "tfmini"},
])
def test_that_a_bad_setting_is_refused_with_its_name(bad):
    with pytest.raises(ValueError, match=next(iter(bad)).split("_")[0]):
        TfminiConfig(**bad)


def test_that_models_are_named_as_the_user_names_them():
    assert TfminiModel.named("tf-luna").value.max_range_m == 8.0
    with pytest.raises(ValueError, match="known: tfmini, tfmini-s"):
        TfminiModel.named("tfmini-x")
