"""The payload's status lines count what its sample log holds: samples by flag, from the samples' own
flags (a line that counted the LiDAR driver's failed transfers said "sensor errors 0" beside a log of
SENSOR_ERROR samples: readings taken while the part reloads after an automatic reset)."""

from __future__ import annotations

import contextlib
import io
import re
import threading
import time

import numpy as np
import pytest

from firmware_py.app import PayloadApp, PayloadConfig
from firmware_py.core.samplelog import SampleFlags, read_samplelog
from firmware_py.hal import pwm as pwm_backends
from firmware_py.hal.backends import unregister_i2c_backend
from firmware_py.hal.clock import MonotonicClock

pytest.importorskip("sitl", reason="the firmware against the simulator (sitl/): not in the payload-only install")
from sitl.devices.i2c_sim import SimI2CBus, register_sim_bus
from sitl.devices.lidarlite_emu import EmulatedLidarLite
from sitl.devices.servo_emu import EmulatedServo


class WallSimClock(MonotonicClock):
    def advance_by_ns(self, dt_ns: int) -> None:
        pass


@contextlib.contextmanager
def emulated_rig(i2c_url: str, pwm_scheme: str, range_m: float):
    """A LIDAR-Lite ranging range_m on the I2C URL i2c_url and the servo on pwm:<pwm_scheme>, unregistered after."""
    clock = WallSimClock()
    bus = SimI2CBus(clock)
    bus.attach(0x62, EmulatedLidarLite(clock, lambda _t_ns: range_m))
    register_sim_bus(bus, i2c_url)
    pwm_backends.register_pwm_backend(pwm_scheme, lambda _url: EmulatedServo(clock))
    try:
        yield
    finally:
        unregister_i2c_backend(i2c_url)
        pwm_backends.unregister_pwm_backend(pwm_scheme)


@pytest.fixture
def stuck_at_zero():
    """A LIDAR-Lite stuck reading 0 cm (PX4's known state: the driver resets it every 20 readings),
    and the servo."""
    with emulated_rig("stuck", "emustatus", 0.004):
        yield


def test_that_the_stop_line_counts_the_sensor_error_samples_the_log_holds_resets_included(tmp_path,
                                                                                          stuck_at_zero):
    cfg = PayloadConfig(out_path=tmp_path / "samples.pslog", mavlink_url="udpout:127.0.0.1:9", i2c_url="stuck",
                        pwm_url="pwm:emustatus", fsync=False, records_per_block=100, quiet=False)
    err = io.StringIO()
    app = PayloadApp(cfg, err=err)

    def stop_after_a_reset():  # the driver resets a part stuck at 0 cm after 20 readings
        deadline = time.monotonic() + 60.0
        while time.monotonic() < deadline:
            lidar = app.lidar
            if lidar is not None and lidar.counters().resetting > 0:
                break
            time.sleep(0.02)
        time.sleep(0.3)
        app.request_stop("test over")

    threading.Thread(target=stop_after_a_reset, daemon=True).start()
    res = app.run()
    flags = read_samplelog(cfg.out_path).samples["flags"]
    in_log = int(np.count_nonzero(flags & SampleFlags.SENSOR_ERROR))
    no_return = int(np.count_nonzero(flags & SampleFlags.NO_RETURN))
    assert in_log > 0 and res.lidar_counters["bus_errors"] + res.lidar_counters["timeouts"] == 0  # the case
    line = [ln for ln in err.getvalue().splitlines() if "stopped (test over)" in ln][-1]
    assert f"sensor error {in_log}" in line and f"no return {no_return}" in line
    assert re.search(rf": {len(flags)} samples \(usable {int(np.count_nonzero(flags == 0))};", line)


@pytest.fixture
def rig_without_an_autopilot():
    """A LIDAR-Lite ranging 5 m and the servo; nothing answers on the MAVLink URL."""
    with emulated_rig("alone", "emualone", 5.0):
        yield


def test_that_the_status_line_says_whole_that_the_autopilot_is_not_heard_naming_the_link(tmp_path,
                                                                                      rig_without_an_autopilot):
    """A walkthrough with no autopilot read "no pose yet (waiting for TIMESYNC replies from the autopilot (system 1);
    no pose can be time-tagged unt)": cut mid-word, and silent on the fact to act on, that nothing answers."""
    url = "udpout:127.0.0.1:9"  # the discard port: nobody answers
    cfg = PayloadConfig(out_path=tmp_path / "samples.pslog", mavlink_url=url, i2c_url="alone", pwm_url="pwm:emualone",
                        fsync=False, records_per_block=100, quiet=False, status_period_s=0.2, duration_s=0.7)
    err = io.StringIO()
    PayloadApp(cfg, err=err).run()
    lines = [ln for ln in err.getvalue().splitlines() if "no pose yet" in ln]
    assert lines, err.getvalue()
    for line in lines:
        assert re.search(rf"no pose yet \(no HEARTBEAT from the autopilot \(system 1\) on {re.escape(url)} for \d+ s: "
                         r"is it connected, is the link's URL right\?\)$", line), line
