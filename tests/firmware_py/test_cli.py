"""`pilescan-payload`'s command line: options map onto PayloadConfig; bad input is one line and exit 2."""

from __future__ import annotations

import math
import os
import signal
from importlib.util import find_spec

import numpy as np
import pytest

from firmware_py.cli import build_parser, config_from_args, hal_urls, main, stop_on_signals
from firmware_py.core.cli import ExitCode, UserError
from firmware_py.core.frames import StorageFrame
from firmware_py.core.samplelog import SampleFlags, read_samplelog
from firmware_py.core.site import Site
from firmware_py.core.version import __version__, software_version
from firmware_py.hal import pwm as pwm_backends
from firmware_py.hal.backends import unregister_i2c_backend
from firmware_py.hal.clock import MonotonicClock
from firmware_py.hal.mavlink_link import MavlinkFramer

# Both are absent on the payload-only install (Raspberry Pi): the tests that need them skip there.
SIM = find_spec("sitl") is not None and find_spec("ground") is not None
if SIM:
    from ground.live_receiver import LiveStreamReceiver
    from sitl.devices.i2c_sim import SimI2CBus, register_sim_bus
    from sitl.devices.lidarlite_emu import EmulatedLidarLite
    from sitl.devices.servo_emu import EmulatedServo
    from tests.firmware_py.autopilot_process import Autopilot
needs_sim = pytest.mark.skipif(not SIM, reason="needs the simulator (sitl/), not in the payload-only install")

NOBODY = "udpout:127.0.0.1:9"  # the discard port: no autopilot there


class WallSimClock(MonotonicClock):
    def advance_by_ns(self, dt_ns: int) -> None:
        pass


@pytest.fixture
def devices():
    if not SIM:
        pytest.skip("needs the simulator (sitl/), not in the payload-only install")
    clock = WallSimClock()
    bus = SimI2CBus(clock)
    bus.attach(0x62, EmulatedLidarLite(clock, lambda _t: 7.5))
    register_sim_bus(bus, "sitl")
    servo = EmulatedServo(clock)
    pwm_backends.register_pwm_backend("emu", lambda _url: servo)
    yield servo
    unregister_i2c_backend("sitl")
    pwm_backends.unregister_pwm_backend("emu")


def parse(*argv: str):
    return config_from_args(build_parser().parse_args(["--out", "x.pslog", *argv]))


def run_bad(capsys, *argv: str, code: ExitCode = ExitCode.USAGE) -> str:
    rc = main(list(argv))
    err = capsys.readouterr().err
    assert rc == code, err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err
    return err


def test_that_version_prints_the_software_version_and_exits_0(capsys):
    assert main(["--version"]) == 0
    out = capsys.readouterr().out
    assert out.strip() == software_version() and __version__ in out


def test_that_defaults_are_the_raspberry_pi_rig_at_500_hz():
    cfg = parse()
    assert (cfg.mavlink_url, cfg.i2c_url, cfg.pwm_url) == ("udpout:127.0.0.1:14550", "i2c:1", "pwm:sysfs:0:0")
    assert (cfg.preset, cfg.rate_hz, cfg.waveform, cfg.servo_peak_rate_rad_s, cfg.initial_position) == (
        "fast-500hz", 500.0, "semi-triangular", 5.0, 0)
    assert cfg.lever_arm_body_m == (0.0, 0.0, 0.10) and cfg.storage.length_m == 60.0
    assert cfg.duration_s is None and not cfg.stop_on_disarm and cfg.stream_url is None and cfg.send_origin is None


def test_that_every_option_reaches_the_config():
    cfg = parse("--mavlink", "serial:/dev/ttyAMA0:921600", "--i2c", "i2c:/dev/i2c-3", "--pwm", "pwm:pca9685:1:0x40:2",
                "--preset", "default", "--rate", "250", "--waveform", "sinusoidal", "--servo-rate", "4",
                "--phase", "13", "--storage", "30x20x10", "--lever-arm", "0.1", "-0.05", "0.2", "--duration", "60",
                "--stop-on-disarm", "--stream", "udp:10.0.0.2:14600", "--send-origin", "53.5", "-2.2", "40",
                "--quiet", "--force", "--mission-id", "abc123")
    assert (cfg.mavlink_url, cfg.i2c_url, cfg.pwm_url) == ("serial:/dev/ttyAMA0:921600", "i2c:/dev/i2c-3",
                                                           "pwm:pca9685:1:0x40:2")
    assert (cfg.preset, cfg.rate_hz, cfg.waveform, cfg.servo_peak_rate_rad_s, cfg.initial_position) == (
        "default", 250.0, "sinusoidal", 4.0, 13)
    assert (cfg.storage.length_m, cfg.storage.width_m, cfg.storage.height_m) == (30.0, 20.0, 10.0)
    assert cfg.lever_arm_body_m == (0.1, -0.05, 0.2) and cfg.duration_s == 60.0 and cfg.stop_on_disarm
    assert cfg.stream_url == "udp:10.0.0.2:14600" and cfg.send_origin == (53.5, -2.2, 40.0)
    assert cfg.quiet and cfg.force and cfg.mission_id == "abc123"


def test_that_origin_places_the_site_sends_its_corner_and_turns_the_frame():
    cfg = parse("--origin=-33.9,151.2,30", "--heading", "30")
    assert cfg.site == Site.of(-33.9, 151.2, 30.0, 30.0) and cfg.send_origin == (-33.9, 151.2, 30.0)
    assert cfg.frame == StorageFrame((0.0, 0.0, 0.0), math.radians(30.0))
    assert cfg.log_header()["site"] == {"lat_deg": -33.9, "lon_deg": 151.2, "alt_m": 30.0, "heading_deg": 30.0}


def test_that_with_another_ekf_origin_sent_the_frame_is_the_site_about_that_origin():
    east_10m = math.degrees(10.0 / (6_378_137.0 * math.cos(math.radians(-33.9))))
    cfg = parse("--origin=-33.9,151.2,30", "--heading", "30", "--send-origin", "-33.9", str(151.2 - east_10m), "31")
    assert cfg.send_origin == (-33.9, 151.2 - east_10m, 31.0)
    assert cfg.frame.origin_ned_m == pytest.approx((0.0, 10.0, 1.0), abs=1e-6)  # the corner: 10 m east, 1 m down
    assert cfg.frame.heading_rad == pytest.approx(math.radians(30.0))


def test_that_heading_alone_turns_the_frame_about_the_autopilots_own_origin_and_sends_nothing():
    cfg = parse("--heading", "-90")
    assert cfg.site is None and cfg.send_origin is None and "site" not in cfg.log_header()
    assert cfg.frame == StorageFrame((0.0, 0.0, 0.0), math.radians(-90.0))
    assert parse().frame == StorageFrame() and parse().site is None


def test_that_hal_sitl_points_i2c_and_pwm_at_the_device_bridge():
    assert hal_urls("sitl:127.0.0.1:5761") == ("tcp:127.0.0.1:5761", "pwm:tcp:127.0.0.1:5761:0")
    cfg = parse("--hal", "sitl:sim-host:6000")
    assert (cfg.i2c_url, cfg.pwm_url) == ("tcp:sim-host:6000", "pwm:tcp:sim-host:6000:0")


@pytest.mark.parametrize(("argv", "word"), [
    (["--preset", "warp-speed"], "preset"),
    (["--rate", "0"], "rate"),
    (["--preset", "default", "--rate", "500"], "faster preset"),
    (["--rate", "nan"], "rate"),
    (["--mavlink", "carrier-pigeon"], "MAVLink link scheme"),
    (["--mavlink", "bogus:x"], "MAVLink link scheme"),
    (["--i2c", "spi:0"], "I2C bus URL"),
    (["--i2c", "tcp:nohostport"], "device bridge URL"),
    (["--mavlink", "udpout:127.0.0.1:99999"], "port"),
    (["--i2c", "i2c:one"], "I2C bus URL"),
    (["--pwm", "servo"], "PWM output"),
    (["--hal", "sitl:localhost"], "--hal"),
    (["--hal", "tcp:localhost:5761"], "--hal"),
    (["--hal", "sitl:localhost:0"], "--hal"),
    (["--hal", "sitl:localhost:5761", "--i2c", "i2c:1"], "--hal"),
    (["--stream", "tcp:10.0.0.2:14600"], "stream"),
    (["--storage", "60x40"], "storage"),
    (["--phase", "20"], "initial position"),
    (["--waveform", "square"], "waveform"),
    (["--duration", "-1"], "duration"),
    (["--lever-arm", "0", "0"], "lever-arm"),
    (["--send-origin", "0", "200", "0"], "longitude"),
    (["--no-such-option"], "unrecognized"),
])
def test_that_bad_options_are_one_line_and_exit_2(capsys, tmp_path, argv, word):
    out = tmp_path / "x.pslog"
    link = [] if "--mavlink" in argv else ["--mavlink", NOBODY]
    err = run_bad(capsys, "--out", str(out), *link, *argv)
    assert word.lower() in err.lower()
    assert not out.exists()


def test_that_a_missing_out_is_a_usage_error(capsys):
    err = run_bad(capsys)
    assert "--out" in err


def test_that_an_existing_log_is_not_overwritten_without_force(capsys, tmp_path, devices):
    out = tmp_path / "x.pslog"
    out.write_bytes(b"yesterday's survey")
    err = run_bad(capsys, "--out", str(out), "--mavlink", NOBODY, "--i2c", "sitl", "--pwm", "pwm:emu")
    assert "already exists" in err and "--force" in err
    assert out.read_bytes() == b"yesterday's survey"
    assert devices.pulses == 0  # refused before touching the hardware


def test_that_hardware_that_cannot_be_opened_is_named_in_one_line(capsys, tmp_path):
    out = tmp_path / "x.pslog"
    err = run_bad(capsys, "--out", str(out), "--mavlink", NOBODY, "--i2c", "i2c:/dev/i2c-nonexistent-77",
                  code=ExitCode.RUNTIME)
    assert "i2c:/dev/i2c-nonexistent-77" in err
    assert not out.exists()


def test_that_an_unreachable_device_bridge_is_named_in_one_line(capsys, tmp_path):
    err = run_bad(capsys, "--out", str(tmp_path / "x.pslog"), "--mavlink", NOBODY, "--hal", "sitl:127.0.0.1:9",
                  code=ExitCode.RUNTIME)
    assert "127.0.0.1:9" in err


def test_that_a_missing_sysfs_pwm_is_named_in_one_line(capsys, tmp_path, devices):
    err = run_bad(capsys, "--out", str(tmp_path / "x.pslog"), "--mavlink", NOBODY, "--i2c", "sitl",
                  "--pwm", "pwm:sysfs:97:0", code=ExitCode.RUNTIME)
    assert "pwm:sysfs:97:0" in err


def test_that_a_timed_run_exits_0_with_a_readable_log(capsys, tmp_path, devices):
    out = tmp_path / "x.pslog"
    handlers = (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM))
    rc = main(["--out", str(out), "--mavlink", NOBODY, "--i2c", "sitl", "--pwm", "pwm:emu", "--duration", "0.4",
               "--rate", "200", "--quiet"])
    assert rc == 0 and capsys.readouterr().err == ""
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == handlers  # restored
    log = read_samplelog(out)
    assert log.intact and len(log.samples) > 10
    assert np.all(log.samples["flags"] & SampleFlags.NO_POSE)  # no autopilot: nothing can be placed
    assert log.header["sensor"]["rate_hz"] == 200.0
    assert not devices.enabled  # the servo was let go at the end


def test_that_stop_on_signals_routes_the_signal_to_the_stop_callback_and_restores():
    reasons = []
    before = signal.getsignal(signal.SIGTERM)
    with stop_on_signals(reasons.append):
        signal.raise_signal(signal.SIGTERM)
    assert reasons == ["signal SIGTERM"]
    assert signal.getsignal(signal.SIGTERM) is before


def test_that_hal_urls_refuses_anything_but_sitl_host_port():
    for bad in ("sitl", "sitl:host", "sitl:host:port", "sitl:host:70000", "i2c:1"):
        with pytest.raises(UserError):
            hal_urls(bad)


# ----- link security ------------------------------------------------------------------------------

KEY = bytes(range(1, 33))


def key_file(tmp_path, mode: int = 0o600, text: str = KEY.hex()):
    path = tmp_path / "link.key"
    path.write_text(text + "\n")
    path.chmod(mode)
    return path


def test_that_a_signing_key_reaches_the_config(tmp_path):
    cfg = parse("--signing-key", str(key_file(tmp_path)))
    assert cfg.signing.key == KEY and not cfg.signing.allow_unsigned and cfg.signing.link_id == 0
    assert KEY.hex() not in repr(cfg)
    assert parse("--signing-key", str(key_file(tmp_path)), "--allow-unsigned").signing.allow_unsigned
    assert parse().signing is None


@pytest.mark.parametrize(("argv", "word", "code"), [
    (["--signing-key", "/nonexistent"], "does not exist", ExitCode.INPUT),
    (["--allow-unsigned"], "--allow-unsigned needs --signing-key", ExitCode.USAGE),
])
def test_that_a_bad_signing_key_is_one_line_and_exit_3_and_a_key_flag_alone_2(capsys, tmp_path, argv, word, code):
    out = tmp_path / "x.pslog"
    err = run_bad(capsys, "--out", str(out), "--mavlink", NOBODY, *argv, code=code)
    assert word in err and not out.exists()


@pytest.mark.skipif(os.name != "posix", reason="POSIX permission bits")
def test_that_a_world_readable_or_empty_signing_key_is_one_line_and_exit_3(capsys, tmp_path):
    err = run_bad(capsys, "--out", str(tmp_path / "x.pslog"), "--signing-key", str(key_file(tmp_path, 0o644)),
                  code=ExitCode.INPUT)
    assert "chmod 600" in err
    err = run_bad(capsys, "--out", str(tmp_path / "x.pslog"), "--signing-key", str(key_file(tmp_path, text="")),
                  code=ExitCode.INPUT)
    assert "empty" in err


@needs_sim
def test_that_a_signed_payload_flies_on_a_signed_autopilot_and_streams_authenticated(capsys, tmp_path, devices):
    out, tlog = tmp_path / "x.pslog", tmp_path / "autopilot.tlog"
    ap = Autopilot(signing_key=KEY, tlog=tlog)  # signed, in a process of its own
    rx = LiveStreamReceiver("udp:127.0.0.1:0", key=KEY, allowed_peers=["127.0.0.1"])
    try:
        rc = main(["--out", str(out), "--mavlink", ap.url, "--i2c", "sitl", "--pwm", "pwm:emu", "--duration", "2.0",
                   "--rate", "200", "--signing-key", str(key_file(tmp_path)),
                   "--stream", f"udp:127.0.0.1:{rx.local_address[1]}"])
        streamed = rx.poll()
    finally:
        ap.close()
        rx.close()
    err = capsys.readouterr().err
    assert rc == 0, err
    assert "MAVLink signing on (link id 0, unsigned frames refused), stream authenticated" in err
    s = read_samplelog(out).samples
    assert np.count_nonzero(s["flags"] == 0) > 50  # signed poses arrived and placed the samples
    assert len(streamed) == len(s) and streamed.tobytes() == s.tobytes()
    assert rx.stats["bad_tag"] == rx.stats["unauthenticated"] == rx.stats["replayed"] == rx.stats["rejected_peer"] == 0
    st = ap.stats()
    assert st["rx_signed"] == st["rx_messages"] > 0 and st["rx_unsigned"] == st["rx_bad_signature"] == 0
    texts = [m.text for m in MavlinkFramer().feed(tlog.read_bytes()) if m.get_type() == "STATUSTEXT"]
    assert "pilescan: started, 200 Hz, link signed" in texts


def test_that_q_and_v_reach_the_payload_and_exclude_each_other(capsys, tmp_path):
    assert parse("-q").quiet and not parse().quiet
    assert build_parser().parse_args(["--out", "x.pslog", "-v"]).verbose
    err = run_bad(capsys, "--out", str(tmp_path / "x.pslog"), "--mavlink", NOBODY, "-q", "-v")
    assert "exclude each other" in err and not (tmp_path / "x.pslog").exists()
