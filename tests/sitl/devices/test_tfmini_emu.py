"""The emulated TFMini: the payload's driver reads it in lockstep (in memory) and over a real
pseudo-terminal with pyserial, the code path a Raspberry Pi's UART takes."""

import statistics
import threading
import time

import pytest

from firmware_py.drivers.reading import ReadStatus
from firmware_py.drivers.tfmini import Frame, FrameParser, Tfmini, TfminiConfig, TfminiModel, classify
from firmware_py.hal.clock import MonotonicClock, SimClock
from firmware_py.hal.uart import open_uart
from sitl.devices.tfmini_emu import EmulatedTfminiPort, PtyTfmini, frame_for

S = TfminiModel.TFMINI_S


def _ranges(t_ns):
    """A target that moves 1 m/s away from 2 m (beyond the 12 m rating after 10 s), then nothing."""
    r = 2.0 + t_ns * 1e-9
    return r if r < 13.0 else None


@pytest.mark.parametrize("model", list(TfminiModel), ids=lambda m: m.value.name)
@pytest.mark.parametrize("r", [None, 0.05, 0.5, 5.0, 7.9, 11.9, 12.5, 30.0])
def test_that_the_emulated_frame_reads_back_as_the_model_reports_it(model, r):
    v = model.value
    frame = Frame.from_bytes(frame_for(v, r))
    range_m, status = classify(frame, v)
    if r is not None and v.min_range_m <= r <= v.max_range_m and not (v.max_is_out_of_range and r >= v.max_range_m):
        assert status == ReadStatus.OK and range_m == pytest.approx(r, abs=0.005)
    else:
        assert status == ReadStatus.NO_RETURN


def test_that_lockstep_readings_match_the_true_range_at_their_time_stamps():
    clock = SimClock()
    port = EmulatedTfminiPort(clock, _ranges, model=S)
    lidar = Tfmini(port, clock, TfminiConfig(model=S))
    period = 10_000_000
    readings = []
    for k in range(1, 1500):  # 15 s at 100 Hz: the loop ticks on the frame grid, a little late
        clock.sleep_until_ns(k * period + 1_234_567)
        readings.append(lidar.read())
    ok = [r for r in readings if r.status == ReadStatus.OK]
    assert len(ok) == pytest.approx(1000, abs=3)  # 10 s in range
    for r in ok:  # the stamp is the measurement time to within a poll: range error <= 1 mm/ms
        assert r.range_m == pytest.approx(_ranges(r.t_ns), abs=0.005 + 1e-4)
    assert all(r.status == ReadStatus.NO_RETURN for r in readings[-300:])
    c = lidar.counters()
    assert c.timeouts == c.bad_checksums == c.dropped_backlog == 0


def test_that_corrupt_frames_are_dropped_and_counted_never_read_as_ranges():
    clock = SimClock()
    port = EmulatedTfminiPort(clock, lambda t: 4.0, model=S, bad_frames=0.2)
    lidar = Tfmini(port, clock, TfminiConfig(model=S))
    got = [lidar.read() for _ in range(500)]
    assert all(r.range_m == 4.0 for r in got if r.status == ReadStatus.OK)
    assert lidar.counters().bad_checksums == port.source.bad_frames_sent > 50


def test_that_an_unplugged_lockstep_sensor_times_out():
    clock = SimClock()
    port = EmulatedTfminiPort(clock, lambda t: 4.0, model=S)
    lidar = Tfmini(port, clock, TfminiConfig(model=S))
    assert lidar.read().status == ReadStatus.OK
    port.unplugged = True
    assert [lidar.read().status for _ in range(3)] == [ReadStatus.TIMEOUT] * 3


def _oks(lidar, n, max_reads=1000):
    """The first n OK readings (a busy machine may delay the writer past a read's deadline: a TIMEOUT
    then, which is the driver working, not the test's subject)."""
    got = []
    for _ in range(max_reads):
        r = lidar.read()
        assert r.status in (ReadStatus.OK, ReadStatus.TIMEOUT)
        if r.ok:
            got.append(r)
            if len(got) == n:
                return got
    raise AssertionError(f"only {len(got)} of {n} readings in {max_reads} reads")


def test_that_pyserial_reads_the_emulated_part_over_a_pseudo_terminal():
    with PtyTfmini(lambda t: 3.21, model=S) as pty:
        port = open_uart(f"serial:{pty.path}:115200")
        try:
            lidar = Tfmini(port, MonotonicClock(), TfminiConfig(model=S))
            got = _oks(lidar, 10)
            pty.inject(b"\x00\xff\x59\x13noise\r\n")  # a loose wire between two frames
            got += _oks(lidar, 10)
        finally:
            port.close()
    assert all(r.range_m == 3.21 for r in got)
    assert lidar.counters().skipped_bytes >= 8  # the noise, skipped


def test_that_an_unplugged_pty_sensor_gives_errors_not_a_hang_or_traceback():
    pty = PtyTfmini(lambda t: 3.21, model=S).start()
    port = open_uart(f"serial:{pty.path}")
    try:
        lidar = Tfmini(port, MonotonicClock(), TfminiConfig(model=S))
        assert _oks(lidar, 1)
        pty.remove_adapter()
        t0 = time.monotonic()
        statuses = {lidar.read().status for _ in range(5)}
        assert time.monotonic() - t0 < 30  # bounded by the 30 ms deadline per read, generously
        assert statuses <= {ReadStatus.BUS_ERROR, ReadStatus.TIMEOUT, ReadStatus.OK}
        assert ReadStatus.BUS_ERROR in statuses or ReadStatus.TIMEOUT in statuses
    finally:
        port.close()
        pty.close()


def _wait_until(condition, timeout_s: float, what: str) -> None:
    end = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < end, f"no {what} within {timeout_s:g} s"
        time.sleep(0.01)


def _bounded(action, timeout_s: float) -> float:
    """Run action in a thread; fail unless it returns within timeout_s (a blocked write would hang the test);
    returns the seconds it took."""
    t0 = time.monotonic()
    worker = threading.Thread(target=action, daemon=True)
    worker.start()
    worker.join(timeout_s)
    assert not worker.is_alive(), f"{getattr(action, '__name__', action)} still blocked after {timeout_s:g} s"
    return time.monotonic() - t0


def test_that_a_pty_nobody_reads_loses_what_does_not_fit_and_stops_at_once():
    """A real TFMini streams whether anyone reads or not (serve with no payload yet, or after it exited): the
    pty's buffer fills and what does not fit is lost, never waited for; so close() (serve's SIGTERM) is prompt,
    and a payload that opens the port later reads the part again."""
    pty = PtyTfmini(lambda t: 3.21, model=S)
    try:
        def fill():  # 256 KB: more than any pty buffer holds (about 20 KB on Linux)
            for _ in range(64):
                pty.inject(bytes(4096))
        _bounded(fill, 10.0)
        assert pty.bytes_dropped > 0  # the buffer is full
        pty.start()
        _wait_until(lambda: pty.frames_dropped >= 3, 5.0, "frames lost to the full buffer")
        port = open_uart(f"serial:{pty.path}")
        try:
            lidar = Tfmini(port, MonotonicClock(), TfminiConfig(model=S))
            lidar.discard_input()  # what the payload does before its readings start
            assert all(r.range_m == 3.21 for r in _oks(lidar, 10))
        finally:
            port.close()
    finally:
        took = _bounded(pty.close, 5.0)
    assert not pty.running and took < 2.5  # STOP_TIMEOUT_S is the bound; the writer ends within a frame


def test_that_the_serial_url_is_checked_before_anything_is_opened():
    with pytest.raises(ValueError, match="baud 1234"):
        open_uart("serial:/dev/ttyUSB0:1234")
    with pytest.raises(ValueError, match="malformed serial port URL"):
        open_uart("serial:ttyUSB0")
    with pytest.raises(OSError, match="cannot open serial port /dev/nonexistent-tty"):
        open_uart("serial:/dev/nonexistent-tty")


def test_that_the_parser_and_emulator_agree_on_every_byte():
    p = FrameParser()
    frames = b"".join(frame_for(S.value, 0.1 * k) for k in range(1, 120))
    got = p.feed(frames)
    assert len(got) == 119 and p.bad_checksums == p.skipped_bytes == 0


def test_that_the_tfmini_emulator_takes_the_same_noise_model_and_its_no_returns_read_as_weak_frames():
    from firmware_py.core.sensor import TFMINI_S
    from firmware_py.core.sensor_noise import SensorNoise
    from sitl.sensing.noise import RangeNoiser, noise_streams

    def readings(range_m):
        clock = SimClock()
        noiser = RangeNoiser(SensorNoise.of("datasheet", TFMINI_S), noise_streams(0), incidence=lambda: 1.0)
        port = EmulatedTfminiPort(clock, lambda t: range_m, model=S, range_noise=noiser)
        lidar = Tfmini(port, clock, TfminiConfig(model=S))
        out = []
        for k in range(1, 1001):
            clock.sleep_until_ns(k * 10_000_000 + 1_234_567)
            out.append(lidar.read())
        return out

    near = [r.range_m for r in readings(3.0) if r.status == ReadStatus.OK]
    assert len(near) > 990
    assert statistics.pstdev(near) == pytest.approx(0.06, rel=0.1)  # the manual's +-6 cm below 6 m
    # 10 m is inside the 12 m rating on a 90 % board but beyond 6.9 m on the model's 30 % target
    assert all(r.status == ReadStatus.NO_RETURN for r in readings(10.0)[5:])
