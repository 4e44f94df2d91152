"""`pilescan-payload --preflight`'s judgements (firmware_py.preflight), each on its own: what a line says of what the
preflight saw. The program around them, on emulated parts: tests/firmware_py/test_app_preflight.py."""

from __future__ import annotations

import math

import numpy as np
import pytest

from firmware_py.preflight import (
    Check,
    PreflightResult,
    Verdict,
    pose_check,
    rangefinder_check,
    sweep_check,
)

FLOOR_BELOW_M, WALL_BESIDE_M = 0.3, 4.0
SWEEP = math.pi / 2
LIDARLITE_SIGMA = (0.025, 0.01)


def room_range_m(angle_rad: float) -> float:
    """The beam from a drone on the ground: the floor FLOOR_BELOW_M below, walls WALL_BESIDE_M either side."""
    c, s = math.cos(angle_rad), abs(math.sin(angle_rad))
    return min(FLOOR_BELOW_M / c if c > 1e-9 else math.inf, WALL_BESIDE_M / s if s > 1e-9 else math.inf)


# ----- the judgements, on their own ----------------------------------------------------------------------------

def test_that_ranges_that_follow_the_sweep_pass_and_a_beam_left_on_one_spot_fails():
    rng = np.random.default_rng(0)
    angles = SWEEP * np.sin(np.linspace(0.0, 6 * math.pi, 2500))
    swept = np.array([room_range_m(a) for a in angles]) + rng.normal(0.0, 0.025, angles.size)
    ok = sweep_check(angles, swept, SWEEP, *LIDARLITE_SIGMA, "pwm:sysfs:0:0")
    assert ok.verdict is Verdict.OK and "12 of 12 sectors" in ok.detail

    still = FLOOR_BELOW_M + rng.normal(0.0, 0.025, angles.size)  # the servo unpowered: the beam stays down
    stuck = sweep_check(angles, still, SWEEP, *LIDARLITE_SIGMA, "pwm:sysfs:0:0")
    assert stuck.verdict is Verdict.FAIL
    assert "servo powered" in stuck.detail and "pwm:sysfs:0:0" in stuck.detail


def test_that_a_sweep_with_ranges_in_too_few_sectors_is_not_judged():
    angles = SWEEP * np.sin(np.linspace(0.0, 6 * math.pi, 2500))
    down = np.abs(angles) < 0.2  # only straight down returns (the rest: sky, out of range)
    check = sweep_check(angles[down], np.full(down.sum(), 0.3), SWEEP, *LIDARLITE_SIGMA, "pwm:sysfs:0:0")
    assert check.verdict is Verdict.WARN and "cannot tell" in check.detail


@pytest.mark.parametrize(("no_return", "errors", "verdict", "words"), [
    (0, 0, Verdict.OK, "100 % ranged"),
    (0, 50, Verdict.WARN, "wiring"),           # 2 % of the readings failed: worth a look
    (0, 1500, Verdict.FAIL, "wiring"),         # more failed than ranged
    (1800, 0, Verdict.WARN, "covered lens"),
    (2000, 500, Verdict.FAIL, "no range at all"),
])
def test_that_the_rangefinder_check_says_what_its_readings_point_to(no_return, errors, verdict, words):
    readings = 2500
    ranges = np.full(readings - no_return - errors, 1.5)
    check = rangefinder_check(readings, no_return, errors, ranges, 5.0, 500.0, "LIDAR-Lite on i2c:1")
    assert check.verdict is verdict and words in check.detail


def test_that_a_rangefinder_slower_than_configured_is_said():
    check = rangefinder_check(400, 0, 0, np.full(400, 2.0), 5.0, 100.0, "TFMini serial:/dev/serial0")
    assert check.verdict is Verdict.WARN and "80 Hz" in check.detail and "100 Hz configured" in check.detail


def test_that_a_missing_local_position_points_at_the_ekf_origin():
    check = pose_check(0.0, "no local position yet", {"ATTITUDE": 50.0}, 50.0, 2.0, origin_sent=False)
    assert check.verdict is Verdict.FAIL and "--send-origin" in check.detail
    slow = pose_check(1.0, "ok", {"ATTITUDE": 50.0, "LOCAL_POSITION_NED": 10.0}, 50.0, 2.0, origin_sent=False)
    assert slow.verdict is Verdict.WARN and "LOCAL_POSITION_NED 10 Hz" in slow.detail
    gaps = pose_check(0.9, "pose stale", {"ATTITUDE": 50.0, "LOCAL_POSITION_NED": 50.0}, 50.0, 2.0, origin_sent=False)
    assert gaps.verdict is Verdict.WARN and "90 % of the samples posed" in gaps.detail
    fine = pose_check(1.0, "ok", {"ATTITUDE": 50.0, "LOCAL_POSITION_NED": 50.0}, 50.0, 2.0, origin_sent=False)
    assert fine.verdict is Verdict.OK


def test_that_a_warning_passes_and_a_failure_does_not_and_the_ground_station_text_is_short():
    ok = Check("a", Verdict.OK, "fine")
    warn = Check("b", Verdict.WARN, "look")
    fail = Check("servo sweep", Verdict.FAIL, "stuck")
    passed = PreflightResult((ok, warn), 5.0, 2500)
    assert passed.passed and passed.lines()[-1] == "preflight passed with 1 warning"
    assert passed.statustext() == "preflight ok"
    failed = PreflightResult((ok, warn, fail), 5.0, 2500)
    assert not failed.passed and failed.lines()[-1] == "preflight FAILED: servo sweep"
    assert len("pilescan: " + failed.statustext()) <= 50
