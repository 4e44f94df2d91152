"""`pilescan-payload --rangefinder tfmini`: the program with a TFMini on a serial port. What goes wrong at
the start (no port, a bad URL, a silent line, bytes at the wrong baud rate) is one line; a streaming
part paces the loop and its datasheet goes into the header."""

from __future__ import annotations

import os
import threading
import tty
from importlib.util import find_spec

import numpy as np
import pytest

from firmware_py.app import PayloadApp, PayloadConfig
from firmware_py.cli import build_parser, config_from_args, main
from firmware_py.core.cli import ExitCode, UserError
from firmware_py.core.samplelog import SampleFlags, read_samplelog
from firmware_py.core.sensor import LIDARLITE_V3, TFMINI_S, Rangefinder
from firmware_py.drivers.servo import SweepServo
from firmware_py.drivers.tfmini import encode_frame
from firmware_py.hal import pwm as pwm_backends
from firmware_py.hal.clock import SimClock
from firmware_py.payload import LoopConfig, PayloadLoop
from firmware_py.pose import PoseSample

NOBODY = "udpout:127.0.0.1:9"  # the discard port: no autopilot there
SIM = find_spec("sitl") is not None


class _Pwm:
    def __init__(self) -> None:
        self.pulses: list[float] = []

    def set_pulse_us(self, us: float) -> None:
        self.pulses.append(us)

    def disable(self) -> None:
        pass

    def close(self) -> None:
        pass


@pytest.fixture
def pwm():
    out = _Pwm()
    pwm_backends.register_pwm_backend("fake", lambda _url: out)
    yield out
    pwm_backends.unregister_pwm_backend("fake")


class _Pty:
    """A pseudo-terminal that sends whatever `writer(master_fd, stop_event)` writes (a thread)."""

    def __init__(self, writer) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        self.path = os.ttyname(self.slave)
        self.stop = threading.Event()
        self.thread = threading.Thread(target=writer, args=(self.master, self.stop), daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.stop.set()
        self.thread.join(timeout=5)
        os.close(self.master)
        os.close(self.slave)


def _garbage(fd, stop):
    rng = np.random.default_rng(1)
    while not stop.wait(0.005):
        data = rng.integers(0, 256, size=40, dtype=np.uint8)
        data[data == 0x59] = 0x58  # never a header: what a wrong baud rate turns 0x59 0x59 into, near enough
        os.write(fd, data.tobytes())


def _frames(fd, stop):
    while not stop.wait(0.01):
        os.write(fd, encode_frame(523, 3000, 2248))


def parse(*argv: str):
    return config_from_args(build_parser().parse_args(["--out", "x.pslog", *argv]))


def run_bad(capsys, *argv: str, code: ExitCode = ExitCode.USAGE) -> str:
    rc = main(list(argv))
    err = capsys.readouterr().err
    assert rc == code, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    return err


def test_that_the_rangefinder_and_uart_options_reach_the_config():
    cfg = parse("--rangefinder", "tfmini", "--uart", "serial:/dev/ttyAMA0:230400")
    assert cfg.rangefinder is Rangefinder.TFMINI and cfg.uart_url == "serial:/dev/ttyAMA0:230400"
    assert cfg.rate_hz == TFMINI_S.rate_hz and cfg.loop_config().paced_by_sensor
    assert cfg.sensor() == TFMINI_S.to_dict()  # the datasheet that flew, in the header
    assert cfg.tfmini_config().baud == 230400
    default = parse()
    assert default.rangefinder is Rangefinder.LIDARLITE_V3 and default.rate_hz == LIDARLITE_V3.rate_hz
    assert not default.loop_config().paced_by_sensor
    assert parse("--rangefinder", "tfmini").uart_url == "serial:/dev/serial0:115200"  # the Pi's header UART


@pytest.mark.parametrize(("argv", "word"), [
    (["--rangefinder", "sonar"], "unknown rangefinder"),
    (["--uart", "serial:/dev/ttyUSB0"], "--rangefinder tfmini"),
    (["--rangefinder", "tfmini", "--uart", "serial:/dev/ttyUSB0:1234"], "baud 1234"),
    (["--rangefinder", "tfmini", "--uart", "serial:ttyUSB0"], "malformed serial port URL"),
    (["--rangefinder", "tfmini", "--uart", ""], "--uart"),
    (["--rangefinder", "tfmini", "--i2c", "i2c:1"], "--uart"),
    (["--rangefinder", "tfmini", "--preset", "short-range"], "--preset"),
    (["--rangefinder", "tfmini", "--uart", "serial:/dev/ttyS0:9600", "--rate", "1000"], "baud"),  # 9.4 ms a frame
    (["--rangefinder", "tfmini", "--rate", "2000"], "frame rate"),
])
def test_that_bad_tfmini_options_are_one_line_and_exit_2(capsys, tmp_path, argv, word):
    out = tmp_path / "x.pslog"
    err = run_bad(capsys, "--out", str(out), "--mavlink", NOBODY, *argv)
    assert word.lower() in err.lower()
    assert not out.exists()


def test_that_a_missing_serial_port_is_named_in_one_line(capsys, tmp_path, pwm):
    err = run_bad(capsys, "--out", str(tmp_path / "x.pslog"), "--mavlink", NOBODY, "--rangefinder", "tfmini",
                  "--uart", "serial:/dev/ttyNOPE9", "--pwm", "pwm:fake", code=ExitCode.RUNTIME)
    assert "serial:/dev/ttyNOPE9" in err and "cannot open" in err
    assert not (tmp_path / "x.pslog").exists()


@pytest.mark.parametrize(("writer", "words"), [
    (lambda fd, stop: stop.wait(10), "no data from the TFMini"),  # a silent line: not wired, not powered
    (_garbage, "no valid TFMini frame"),  # bytes, never a frame: the wrong baud rate
])
def test_that_a_port_without_frames_stops_the_start_in_one_line(capsys, tmp_path, pwm, writer, words):
    pty = _Pty(writer)
    try:
        err = run_bad(capsys, "--out", str(tmp_path / "x.pslog"), "--mavlink", NOBODY, "--rangefinder", "tfmini",
                      "--uart", f"serial:{pty.path}", "--pwm", "pwm:fake", code=ExitCode.RUNTIME)
    finally:
        pty.close()
    assert words in err and pty.path in err
    assert not (tmp_path / "x.pslog").exists()


def test_that_the_payload_logs_a_streaming_tfmini_one_sample_per_frame(tmp_path, pwm):
    pty = _Pty(_frames)
    try:
        cfg = PayloadConfig(out_path=tmp_path / "s.pslog", mavlink_url=NOBODY, rangefinder=Rangefinder.TFMINI,
                            uart_url=f"serial:{pty.path}", pwm_url="pwm:fake", duration_s=0.5, fsync=False,
                            quiet=True)
        res = PayloadApp(cfg, err=None).run()
    finally:
        pty.close()
    log = read_samplelog(cfg.out_path)
    s = log.samples
    assert log.intact and res.stop_reason == "duration reached"
    assert 20 <= len(s) <= 60  # ~50 frames in 0.5 s (a busy machine may deliver fewer)
    assert np.all(s["range_m"][(s["flags"] & int(SampleFlags.SENSOR_ERROR)) == 0] == pytest.approx(5.23))
    assert log.header["sensor"] == TFMINI_S.to_dict()
    assert log.header["payload"]["uart"] == f"serial:{pty.path}" and "i2c" not in log.header["payload"]
    # every sample that is not a sensor error came from a frame (a busy machine may starve the port's writer, and
    # a tick without a frame is a timeout: a sample flagged, not a frame)
    assert res.lidar_counters["frames"] >= np.count_nonzero((s["flags"] & int(SampleFlags.SENSOR_ERROR)) == 0)


class _Sensor:
    """A streaming sensor on a simulated clock: a reading every 10 ms, read() waits for it."""

    def __init__(self, clock: SimClock, period_ns: int = 10_000_000) -> None:
        self.clock, self.period_ns, self.k = clock, period_ns, 0

    def read(self):
        from firmware_py.drivers.reading import Reading, ReadStatus
        self.k += 1
        t = self.k * self.period_ns + 137_000 + (-1) ** (self.k // 2) * 60_000  # delivery jitters by 60 us
        self.clock.sleep_until_ns(t)
        return Reading(4.0, ReadStatus.OK, t - 800_000, 1)


class _Poses:
    def pump(self) -> None:
        pass

    def pose_at(self, t_ns: int) -> PoseSample:
        nan = float("nan")
        return PoseSample(t_ns, (nan, nan, nan), nan, nan, nan, float("inf"), stale=True, missing=True)


class _Log:
    def __init__(self) -> None:
        self.n = 0

    def append(self, rec) -> None:
        self.n += 1

    def flush(self) -> None:
        pass


def test_that_a_sensor_paced_loop_ticks_on_its_readings_and_drives_the_servo_every_pwm_frame():
    from firmware_py.core.waveform import named_waveform
    clock = SimClock()
    pwm = _Pwm()
    times: list[int] = []
    pwm.set_pulse_us = lambda us: times.append(clock.now_ns())
    servo = SweepServo(pwm, named_waveform("semi-triangular", 5.0, 0), early_s=0.005)
    log = _Log()
    loop = PayloadLoop(_Sensor(clock), servo, _Poses(), clock, log,
                       LoopConfig(rate_hz=100.0, paced_by_sensor=True), t0_ns=0)
    stats = loop.run(duration_s=2.0)
    assert stats.ticks == log.n == pytest.approx(200, abs=1) and stats.overruns == 0
    gaps = np.diff(times[1:])
    assert np.all(np.abs(gaps - 20_000_000) <= 120_000)  # 50 Hz pulses, never one held back a tick


def test_that_config_checks_refuse_a_rangefinder_that_is_not_one():
    with pytest.raises(ValueError, match="rangefinder"):
        PayloadConfig(rangefinder="tfmini")
    with pytest.raises(UserError, match="--uart"):
        parse("--uart", "serial:/dev/ttyS0")


def test_that_a_preflight_with_a_silent_tfmini_says_so_once_and_checks_the_rest(tmp_path, pwm):
    from firmware_py.app import PayloadApp, PayloadConfig
    from firmware_py.core.sensor import Rangefinder
    from firmware_py.preflight import Verdict

    pty = _Pty(lambda fd, stop: stop.wait(10))  # wired to nothing that sends
    try:
        cfg = PayloadConfig(out_path=tmp_path / "x.pslog", mavlink_url=NOBODY, rangefinder=Rangefinder.TFMINI,
                            uart_url=f"serial:{pty.path}", pwm_url="pwm:fake", quiet=True, fsync=False)
        res = PayloadApp(cfg, err=None).preflight(0.5)
    finally:
        pty.close()
    names = [c.name for c in res.checks]
    assert names.count("rangefinder") == 1  # the port opened but sent nothing: one line, not a second "no range"
    checks = {c.name: c for c in res.checks}
    assert checks["rangefinder"].verdict is Verdict.FAIL and "no data from the TFMini" in checks["rangefinder"].detail
    assert checks["servo sweep"].verdict is Verdict.WARN and "not checked" in checks["servo sweep"].detail
    assert checks["autopilot"].verdict is Verdict.FAIL and not (tmp_path / "x.pslog").exists()
