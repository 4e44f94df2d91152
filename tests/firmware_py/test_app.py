"""The payload program end to end, in real time, against the SITL's emulated devices and autopilot.

The rig: an emulated LIDAR-Lite (fixed 5 m range) on a simulated I2C bus registered as `sitl`, an
emulated servo registered as PWM `pwm:emu`, and the SITL's MAVLink autopilot (a kinematic vehicle)
served over UDP in a process of its own (`tests.firmware_py.autopilot_process`), which records what the
payload sends and arms or disarms when the test asks. The payload runs on the real
monotonic clock; nothing asserts on timing, only on what was logged and sent.
"""

from __future__ import annotations

import contextlib
import io
import math
import os
import re
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from firmware_py.app import PayloadApp, PayloadConfig
from firmware_py.core.cli import UserError
from firmware_py.core.samplelog import HEAD_SIZE, SAMPLE_DTYPE, SampleFlags, read_samplelog
from firmware_py.hal import pwm as pwm_backends
from firmware_py.hal.backends import unregister_i2c_backend
from firmware_py.hal.clock import MonotonicClock

pytest.importorskip("ground", reason="the live stream's receiver: not in the payload-only install")
pytest.importorskip("sitl", reason="the firmware against the simulator (sitl/): not in the payload-only install")
from ground.live_receiver import LiveStreamReceiver
from sitl.devices.i2c_sim import SimI2CBus, register_sim_bus
from sitl.devices.lidarlite_emu import EmulatedLidarLite
from sitl.devices.servo_emu import EmulatedServo
from tests.firmware_py.autopilot_process import HOME_NED, Autopilot

pytestmark = pytest.mark.long  # scheduled first (tests/conftest.py)

RANGE_M = 5.0
REPO = Path(__file__).resolve().parents[2]


class WallSimClock(MonotonicClock):
    """Real time for the emulated devices: a transfer's wire time has really passed, nothing to charge."""

    def advance_by_ns(self, dt_ns: int) -> None:
        pass


@contextlib.contextmanager
def emulated_rig(range_at: Callable[[EmulatedServo, int], float | None]):
    """LIDAR-Lite on `sitl` ranging range_at(servo, t_ns), servo on `pwm:emu`, unregistered afterwards."""
    clock = WallSimClock()
    bus = SimI2CBus(clock)
    servo = EmulatedServo(clock)
    lidar = EmulatedLidarLite(clock, lambda t_ns: range_at(servo, t_ns))
    bus.attach(0x62, lidar)
    register_sim_bus(bus, "sitl")
    pwm_backends.register_pwm_backend("emu", lambda _url: servo)
    try:
        yield bus, lidar, servo
    finally:
        unregister_i2c_backend("sitl")
        pwm_backends.unregister_pwm_backend("emu")


@pytest.fixture
def devices():
    """The rig at a fixed range, RANGE_M."""
    with emulated_rig(lambda _servo, _t_ns: RANGE_M) as parts:
        yield parts


@pytest.fixture
def autopilot():
    ap = Autopilot()
    yield ap
    ap.close()


def payload_config(tmp_path: Path, mavlink_url: str, **kw) -> PayloadConfig:
    base = {"out_path": tmp_path / "samples.pslog", "mavlink_url": mavlink_url, "i2c_url": "sitl",
            "pwm_url": "pwm:emu", "fsync": False, "records_per_block": 100, "quiet": True}
    return PayloadConfig(**{**base, **kw})


def stop_later(app: PayloadApp, after_s: float) -> threading.Timer:
    timer = threading.Timer(after_s, app.request_stop, ["test over"])
    timer.daemon = True
    timer.start()
    return timer


# ----- configuration (the rest: tests/firmware_py/test_payload_config.py) -----------------------------

def test_that_a_scheme_another_layer_registered_is_accepted_and_refused_once_it_is_gone(devices):
    PayloadConfig(i2c_url="sitl:0", pwm_url="pwm:emu")  # the fixture's emulated bus and servo
    unregister_i2c_backend("sitl")
    with pytest.raises(ValueError, match="unknown scheme 'sitl'"):
        PayloadConfig(i2c_url="sitl:0", pwm_url="pwm:emu")


# ----- end to end, in process ----------------------------------------------------------------------

def test_that_the_payload_logs_posed_samples_and_reports_health_to_the_autopilot(tmp_path, devices, autopilot):
    _bus, emu_lidar, emu_servo = devices
    receiver = LiveStreamReceiver("udp:127.0.0.1:0")
    streamed = []
    cfg = payload_config(tmp_path, autopilot.url, stream_url=f"udp:127.0.0.1:{receiver.local_address[1]}")
    err = io.StringIO()
    app = PayloadApp(cfg, err=err)
    done = threading.Event()

    def drain():
        while not done.is_set():
            streamed.append(receiver.poll())
            time.sleep(0.02)

    drainer = threading.Thread(target=drain, daemon=True)
    drainer.start()
    stop_later(app, 2.5)
    try:
        res = app.run()
    finally:
        done.set()
        drainer.join(timeout=5.0)
    streamed.append(receiver.poll())
    receiver.close()
    assert autopilot.wait_for(lambda: any("stopping" in t for t in autopilot.texts()))

    assert res.stop_reason == "test over" and res.close_errors == ()
    log = read_samplelog(cfg.out_path)
    assert log.intact and log.header["source"] == "payload"
    assert log.header["autopilot_params"]["EK3_SRC1_POSZ"] == 1.0  # read from the autopilot over UDP at start
    s = log.samples
    assert len(s) == res.records_logged == res.readings > 200
    assert emu_lidar.counters["acquisitions"] >= len(s)
    good = s[s["flags"] == 0]
    assert len(good) > 100, res.pose_status  # the pose arrived and tagged samples
    assert np.all(good["range_m"] == np.float32(RANGE_M))
    assert np.allclose(good["x_m"], HOME_NED[0]) and np.allclose(good["y_m"], HOME_NED[1])
    assert np.allclose(good["z_m"], 0.0) and np.all(np.isfinite(good["yaw_rad"]))
    first_good = np.flatnonzero(s["flags"] == 0)[0]
    assert np.all(s["flags"][:first_good] & (SampleFlags.NO_POSE | SampleFlags.STALE_POSE))
    assert np.all(np.diff(s["t_s"]) > 0)
    assert np.ptp(good["servo_rad"]) > 0.5  # the servo swept

    names = {m.name for m in autopilot.of_type("NAMED_VALUE_FLOAT")}
    assert {"PS_RATE", "PS_I2CERR", "PS_POSEAGE", "PS_STALE", "PS_LOGGED"} <= names
    texts = autopilot.texts()
    assert any(t.startswith("pilescan: started") for t in texts)
    assert "pilescan: pose acquired" in texts
    assert texts[-1] == "pilescan: stopping: test over"
    assert all(len(t) <= 50 for t in texts)
    assert "pilescan: EKF height from rangefinder" not in texts  # a barometer height: nothing to warn of
    assert autopilot.stats()["rx_by_type"]["HEARTBEAT"] >= 1

    assert emu_servo.pulses > 50 and not emu_servo.enabled  # swept, then disabled at shutdown
    got = np.concatenate(streamed)
    assert got.dtype == SAMPLE_DTYPE and len(got) == len(s)
    assert got.tobytes() == s.tobytes()  # the live stream carried exactly the logged records


def test_that_a_full_disk_stops_the_payload_telling_the_operator_why_and_keeps_every_whole_block(
        tmp_path, devices, autopilot):
    import errno

    class FillingFile:  # takes 40 kB, then ENOSPC (the first failing write takes what fits)
        def __init__(self, f):
            self.f, self.room = f, 40_000

        def write(self, data):
            if len(data) > self.room:
                self.f.write(bytes(data)[: self.room])
                self.room = 0
                raise OSError(errno.ENOSPC, "No space left on device")
            self.room -= len(data)
            return self.f.write(data)

        def __getattr__(self, name):
            return getattr(self.f, name)

    cfg = payload_config(tmp_path, autopilot.url, duration_s=20.0)
    with pytest.raises(OSError, match="No space"):
        PayloadApp(cfg, err=None, open_log=lambda path, mode: FillingFile(open(path, mode))).run()
    assert autopilot.wait_for(lambda: "pilescan: stopping: error: No space left on device" in autopilot.texts())
    stop = [m for m in autopilot.of_type("STATUSTEXT") if "No space" in str(m.text)]
    assert stop and all(m.severity == 2 for m in stop)  # MAV_SEVERITY_CRITICAL: the operator should land
    log = read_samplelog(cfg.out_path)
    assert log.blocks_corrupt == 0 and log.blocks_truncated == 1 and len(log.samples) % cfg.records_per_block == 0
    assert len(log.samples) > 0 and log.header["servo_drive"]["t0_s"] <= log.samples["t_s"][0]


def test_that_stop_on_disarm_stops_once_the_autopilot_disarms_after_arming(tmp_path, devices):
    ap = Autopilot(armed=True)
    try:
        cfg = payload_config(tmp_path, ap.url, stop_on_disarm=True, duration_s=20.0)
        app = PayloadApp(cfg, err=None)
        threading.Timer(1.5, ap.disarm).start()
        res = app.run()
    finally:
        ap.close()
    assert res.stop_reason == "autopilot disarmed"  # not "duration reached": the disarm stopped it
    assert read_samplelog(cfg.out_path).intact


def test_that_start_on_arm_logs_from_the_arming_to_the_disarming_and_nothing_on_the_ground(tmp_path, devices):
    _bus, _lidar, servo = devices
    ap = Autopilot()  # on the ground, disarmed
    try:
        cfg = payload_config(tmp_path, ap.url, start_on_arm=True, stop_on_disarm=True, duration_s=20.0)
        app = PayloadApp(cfg, err=None)
        armed_at: list[float] = []
        before_arm: list[tuple[bool, int]] = []

        def arm():
            before_arm.append((cfg.out_path.exists(), servo.pulses))
            armed_at.append(time.monotonic())
            ap.arm()
        threading.Timer(1.0, arm).start()
        threading.Timer(2.5, ap.disarm).start()
        t0 = time.monotonic()
        res = app.run()
        waited_s = armed_at[0] - t0
    finally:
        ap.close()
    assert res.stop_reason == "autopilot disarmed"
    assert before_arm == [(False, 0)]  # while it waited: no log file, not one pulse to the servo
    assert "pilescan: waiting for arm" in ap.texts()
    log = read_samplelog(cfg.out_path)
    assert log.intact and log.header["config"]["payload"]["start_on_arm"] is True
    span_s = float(log.samples["t_s"][-1] - log.samples["t_s"][0])
    assert 0.5 < span_s < res.elapsed_s - waited_s + 0.5  # the flight's samples, none from the wait before it


def test_that_a_payload_stopped_before_the_autopilot_arms_writes_no_log(tmp_path, devices, autopilot):
    cfg = payload_config(tmp_path, autopilot.url, start_on_arm=True, quiet=False)
    err = io.StringIO()
    app = PayloadApp(cfg, err=err)
    stop_later(app, 0.8)
    res = app.run()
    assert res.stop_reason == "test over" and res.records_logged == 0
    assert not cfg.out_path.exists()
    assert "waiting for the autopilot to arm" in err.getvalue()
    assert "before the autopilot armed: no log written" in err.getvalue()


def test_that_the_operator_is_warned_before_the_survey_when_the_autopilot_takes_its_height_from_the_rangefinder(
        tmp_path, devices):
    """Over a stockpile a rangefinder height is the height above the pile: the payload says so on its console and to
    the ground station (STATUSTEXT) at start, from the EKF sources it read, while the parameter can still be set."""
    from sitl.sensing.pose_drift import PoseErrorProfile, ekf_source_params
    ap = Autopilot(params=ekf_source_params(PoseErrorProfile.FLOW))  # optical flow; rangefinder below 70 %
    err = io.StringIO()
    try:
        res = PayloadApp(payload_config(tmp_path, ap.url, duration_s=1.0, quiet=False), err=err).run()
        assert ap.wait_for(lambda: any("stopping" in t for t in ap.texts()))
    finally:
        ap.close()
    assert res.stop_reason == "duration reached"
    out = err.getvalue()
    assert "pose from the autopilot: position optical flow velocity, integrated; height barometer, the downward " \
           "rangefinder below 70 % of its range" in out
    assert "warning: the autopilot takes its height from the downward rangefinder (EK3_RNG_USE_HGT = 70)" in out
    assert "EK3_RNG_USE_HGT = -1" in out  # what to set instead
    texts = ap.texts()
    assert "pilescan: EKF height from rangefinder" in texts and all(len(t) <= 50 for t in texts)
    started = next(i for i, t in enumerate(texts) if t.startswith("pilescan: started"))
    assert texts[started + 1] == "pilescan: EKF height from rangefinder"  # said with the start, before the survey


def test_that_a_nearly_full_log_card_is_said_at_start_on_the_console_and_the_ground_station(tmp_path, devices,
                                                                                          monkeypatch):
    """A payload started flight after flight fills its card with logs; at start it says when the free space holds
    less than half an hour of samples, before the survey is flown, and flies on (the log stops when it is full)."""
    from collections import namedtuple

    from firmware_py import log_room
    ten_minutes = 630 * log_room.log_bytes_per_s(500.0, 100)  # payload_config's 100 records a block
    monkeypatch.setattr(log_room.shutil, "disk_usage", lambda path: namedtuple("U", "total used free")(
        10**10, 10**10 - ten_minutes, ten_minutes))
    ap = Autopilot()
    err = io.StringIO()
    try:
        app = PayloadApp(payload_config(tmp_path, ap.url, duration_s=None, quiet=False), err=err)
        stop_later(app, 1.5)  # no --duration: it would run on
        res = app.run()
        assert ap.wait_for(lambda: any("stopping" in t for t in ap.texts()))
    finally:
        ap.close()
    assert res.stop_reason == "test over"  # a warning, not a refusal: it flew on
    assert "warning: the log's file system has room for 10 min of samples at 500 Hz, less than half an hour" \
        in err.getvalue()
    texts = ap.texts()
    started = next(i for i, t in enumerate(texts) if t.startswith("pilescan: started"))
    assert texts[started + 1] == "pilescan: log storage nearly full"


def test_that_a_disarmed_autopilot_that_never_armed_does_not_stop_the_payload(tmp_path, devices, autopilot):
    cfg = payload_config(tmp_path, autopilot.url, stop_on_disarm=True, duration_s=1.5)
    res = PayloadApp(cfg, err=None).run()
    assert res.stop_reason == "duration reached"
    assert autopilot.armed() is False


def test_that_the_payload_runs_without_an_autopilot_and_flags_every_sample(tmp_path, devices):
    cfg = payload_config(tmp_path, "udpout:127.0.0.1:9", duration_s=0.5, quiet=False)  # nobody listens
    err = io.StringIO()
    res = PayloadApp(cfg, err=err).run()
    s = read_samplelog(cfg.out_path).samples
    assert res.stop_reason == "duration reached" and len(s) == res.records_logged > 0
    assert np.all(s["flags"] & SampleFlags.NO_POSE) and res.records_flagged == len(s)
    assert "stopped (duration reached)" in err.getvalue()
    assert "autopilot_params" not in read_samplelog(cfg.out_path).header  # nobody answered: nothing claimed


def test_that_the_ekf_origin_is_sent_when_asked(tmp_path, devices, autopilot):
    cfg = payload_config(tmp_path, autopilot.url, duration_s=0.5, send_origin=(53.4668, -2.2339, 50.0))
    PayloadApp(cfg, err=None).run()
    assert autopilot.wait_for(lambda: autopilot.of_type("SET_GPS_GLOBAL_ORIGIN"))
    msg = autopilot.of_type("SET_GPS_GLOBAL_ORIGIN")[0]
    assert (msg.latitude, msg.longitude, msg.altitude) == (534668000, -22339000, 50000)


def test_that_an_autopilot_whose_ekf_origin_is_another_point_is_warned_about(tmp_path, devices, autopilot):
    """The header's storage frame is the site about the origin sent; positions about another are wrong."""
    err = io.StringIO()
    cfg = payload_config(tmp_path, autopilot.url, duration_s=2.0, send_origin=(-33.9, 151.2, 30.0))
    app = PayloadApp(cfg, err=err)
    app.run()
    assert autopilot.stats()["origin_refused"] >= 1  # the SITL autopilot's origin is the default site's
    assert app.origin_disagreement is not None and "53.4668000, -2.2339000, 50 m" in app.origin_disagreement
    assert "warning: the autopilot's EKF origin is 53.4668000" in err.getvalue()


def test_that_an_autopilot_confirming_the_origin_sent_raises_no_warning(tmp_path, devices, autopilot):
    err = io.StringIO()
    app = PayloadApp(payload_config(tmp_path, autopilot.url, duration_s=2.0, send_origin=(53.4668, -2.2339, 50.0)),
                     err=err)
    app.run()
    assert autopilot.stats()["rx_by_type"]["SET_GPS_GLOBAL_ORIGIN"] >= 1
    assert app.tracker.autopilot_origin_e7 == (534668000, -22339000, 50000)
    assert app.origin_disagreement is None and "EKF origin" not in err.getvalue()


def test_that_an_existing_log_is_refused_before_any_hardware_is_opened(tmp_path, devices):
    out = tmp_path / "samples.pslog"
    out.write_bytes(b"precious")
    with pytest.raises(UserError, match="already exists"):
        PayloadApp(payload_config(tmp_path, "udpout:127.0.0.1:9"), err=None).run()
    assert out.read_bytes() == b"precious"
    assert devices[2].pulses == 0


def test_that_a_failed_open_closes_what_was_opened_and_leaves_no_log(tmp_path, devices):
    bus, _lidar, _servo = devices
    bus.detach(0x62)  # no LIDAR-Lite on the bus
    cfg = payload_config(tmp_path, "udpout:127.0.0.1:9")
    app = PayloadApp(cfg, err=None)
    with pytest.raises(UserError, match=r"LIDAR-Lite at 0x62 on sitl"):
        app.run()
    assert not cfg.out_path.exists()
    assert app.link.closed


# ----- as a process: signals -------------------------------------------------------------------------

LAUNCHER = """
import sys
from firmware_py.hal.clock import MonotonicClock
from firmware_py.hal.pwm import register_pwm_backend
from sitl.devices.i2c_sim import SimI2CBus, register_sim_bus
from sitl.devices.lidarlite_emu import EmulatedLidarLite
from sitl.devices.servo_emu import EmulatedServo
from tests.firmware_py.autopilot_process import HOME_NED, Autopilot

class WallSimClock(MonotonicClock):
    def advance_by_ns(self, dt_ns):
        pass

clock = WallSimClock()
bus = SimI2CBus(clock)
bus.attach(0x62, EmulatedLidarLite(clock, lambda t_ns: 5.0))
register_sim_bus(bus, "sitl")
register_pwm_backend("emu", lambda url: EmulatedServo(clock))
from firmware_py.cli import main
raise SystemExit(main(sys.argv[1:]))
"""
"""`python -m firmware_py.cli` with the emulated devices registered first (no device bridge needed)."""

BLOCK = 500
BLOCK_BYTES = HEAD_SIZE + BLOCK * SAMPLE_DTYPE.itemsize


def start_payload(out: Path, mavlink_url: str, *extra: str) -> subprocess.Popen:
    args = [sys.executable, "-c", LAUNCHER, "--out", str(out), "--mavlink", mavlink_url, "--i2c", "sitl",
            "--pwm", "pwm:emu", *extra]
    return subprocess.Popen(args, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})


def wait_for_blocks(proc: subprocess.Popen, out: Path, blocks: int, timeout_s: float = 30.0) -> None:
    """Until the log holds `blocks` full sample blocks past its header (the size says so)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()[1]
        if out.exists() and out.stat().st_size >= blocks * BLOCK_BYTES + 200:
            return
        time.sleep(0.05)
    proc.kill()
    raise AssertionError(f"the payload wrote no {blocks} blocks: {proc.communicate()[1]}")


def test_that_sigterm_stops_the_payload_cleanly_with_a_complete_log(tmp_path, autopilot):
    out = tmp_path / "run.pslog"
    proc = start_payload(out, autopilot.url)
    try:
        wait_for_blocks(proc, out, 1)
        proc.send_signal(signal.SIGTERM)
        _stdout, stderr = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, stderr
    assert "Traceback" not in stderr
    summary = re.search(r"stopped \(signal SIGTERM\) after [0-9.]+ s: (\d+) samples", stderr)
    assert summary is not None, stderr
    log = read_samplelog(out)
    assert log.intact and log.blocks_corrupt == 0 and log.blocks_truncated == 0
    assert len(log.samples) == int(summary.group(1)) > BLOCK  # every sample, the last partial block too
    assert autopilot.wait_for(lambda: "pilescan: stopping: signal SIGTERM" in autopilot.texts())


def test_that_sigint_stops_the_payload_like_sigterm(tmp_path):
    out = tmp_path / "run.pslog"
    proc = start_payload(out, "udpout:127.0.0.1:9", "--quiet")
    try:
        wait_for_blocks(proc, out, 1)
        proc.send_signal(signal.SIGINT)
        _stdout, stderr = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0 and stderr == ""
    assert read_samplelog(out).intact


@pytest.mark.parametrize("seed", [1, 2])
def test_that_sigkill_loses_at_most_the_unfinished_block(tmp_path, seed):
    out = tmp_path / "run.pslog"
    proc = start_payload(out, "udpout:127.0.0.1:9", "--quiet")
    try:
        wait_for_blocks(proc, out, 2)
        time.sleep(np.random.default_rng(seed).uniform(0.0, 1.0))  # anywhere within the next blocks
        proc.kill()
        proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL
    log = read_samplelog(out)
    assert log.header is not None and log.header["source"] == "payload"
    assert log.blocks_corrupt == 0 and log.blocks_truncated <= 1
    assert len(log.samples) >= 2 * BLOCK and len(log.samples) % BLOCK == 0  # every complete block, nothing else
    assert math.isclose(log.samples["range_m"][-1], 5.0)


def test_that_python_m_firmware_py_cli_runs_on_the_sitl_device_bridge_and_stops_on_sigterm(tmp_path, autopilot):
    """The real entry point, unmodified, with --hal sitl:HOST:PORT: the SITL's devices over TCP."""
    bridge_server = pytest.importorskip("sitl.devices.bridge_server")
    clock = WallSimClock()
    bus = SimI2CBus(clock)
    emu = EmulatedLidarLite(clock, lambda _t: RANGE_M)
    bus.attach(0x62, emu)
    servo = EmulatedServo(clock)
    out = tmp_path / "run.pslog"
    with bridge_server.DeviceBridgeServer(bus, {0: servo}) as bridge:
        host, port = bridge.address
        proc = subprocess.Popen(
            [sys.executable, "-m", "firmware_py.cli", "--out", str(out), "--mavlink", autopilot.url,
             "--hal", f"sitl:{host}:{port}", "--rate", "200"],
            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            deadline = time.monotonic() + 30.0
            while emu.counters["acquisitions"] < 200 and time.monotonic() < deadline:
                assert proc.poll() is None, proc.communicate()[1]
                time.sleep(0.05)
            proc.send_signal(signal.SIGTERM)
            _stdout, stderr = proc.communicate(timeout=20)
        finally:
            if proc.poll() is None:
                proc.kill()
    assert proc.returncode == 0 and "Traceback" not in stderr, stderr
    log = read_samplelog(out)
    assert log.intact and len(log.samples) >= 200
    assert len(log.samples) == emu.counters["acquisitions"]  # every reading taken was logged
    assert servo.pulses > 0 and not servo.enabled  # disabled through the bridge at shutdown


def test_that_link_counters_read_a_links_stats_by_name_and_count_refused_frames():
    from firmware_py.app import LinkCounters
    c = LinkCounters.of({"rx_messages": 7, "rx_unsigned": 2, "rx_bad_signature": 1, "rx_replayed": 4, "new": 9})
    assert c.rx_messages == 7 and c.tx_messages == 0 and c.refused == 7


def test_that_both_mavlink_links_offer_what_the_app_reads_of_a_link():
    from firmware_py.app import LinkCounters
    from firmware_py.hal import MavlinkLink
    from firmware_py.hal.mavlink_link import ByteStreamLink, open_mavlink
    wanted = {"mav", "signer", "stats", "signing_active", "send", "recv", "close"}
    assert wanted <= set(MavlinkLink.__annotations__) | {n for n in vars(MavlinkLink) if not n.startswith("_")}
    for link in (ByteStreamLink(lambda data: None, lambda: b""), open_mavlink("udpout:127.0.0.1:9")):
        try:
            assert all(hasattr(link, name) for name in wanted) and link.signer is None and not link.signing_active
            assert LinkCounters.of(link.stats).tx_messages == link.stats["tx_messages"]
        finally:
            link.close()

