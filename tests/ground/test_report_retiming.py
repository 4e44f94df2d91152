"""How the report re-times the servo from the floor and walls: the search's delay refined by the offset they still
show once it is applied (`_refined_by_building`), and an offset as logged that the fit beside the drift does not back
re-timing nothing unless the pile's sweeps confirm it (`timing_to_confirm`)."""

import math

import numpy as np
import pytest

from firmware_py.core.frames import SQUARE, StorageFrame
from firmware_py.core.storage import Storage
from ground import report
from ground.plane_stretches import TimingSplit
from ground.pointcloud import SensorErrorModel
from ground.pose_correction import not_applied
from ground.report import ReportOptions, timing_to_confirm
from ground.servo_timing import LAST_BUT_ONE_STEP_S, ServoTiming

NOISE_M = 0.05


def _split(delay_s: float, sigma_s: float, shift_m: float) -> TimingSplit:
    return TimingSplit(0.1, delay_s, sigma_s, shift_m)


def _pose(fit: TimingSplit | None, raw: TimingSplit | None):
    return not_applied("a test's", servo_delay=fit, servo_delay_raw=raw, noise_m=NOISE_M)


def test_that_an_offset_as_logged_the_drift_fit_does_not_back_is_only_a_hint_to_confirm():
    """10 ms as logged, measured and moving the points more than their noise, where the fit beside the drift read
    3 ms at not quite three standard errors: not the floor and walls' call alone (`structure_timing`), but a timing
    for the pile's sweeps to confirm. One not measured, or too small to matter, or none, is no hint."""
    raw = _split(0.00987, 0.00027, 0.178)
    pose = _pose(_split(0.0030, 0.00102, 0.06), raw)
    assert report.structure_timing(pose) is None
    assert timing_to_confirm(pose) == raw
    assert timing_to_confirm(_pose(None, _split(0.0005, 0.0003, 0.178))) is None  # under 3 standard errors
    assert timing_to_confirm(_pose(None, _split(0.0073, 0.0001, 0.01))) is None  # moves the points less than noise
    assert timing_to_confirm(_pose(None, None)) is None
    assert timing_to_confirm(None) is None


class _Motion:
    """A servo motion that records the delays it re-timed the samples by."""

    name = "servo model"

    def __init__(self) -> None:
        self.applied: list[tuple[float, float]] = []

    def apply(self, samples: np.ndarray, delay_s: float, gain: float) -> np.ndarray:
        self.applied.append((delay_s, gain))
        return samples


def _refined(monkeypatch, left: TimingSplit | None, fit: bool = True, pose_correction: bool = True):
    """The search's 9 ms refined where the floor and walls, on the samples it re-timed, show `left` (beside the drift's
    fit when fit, else as logged with no such fit)."""
    monkeypatch.setattr(report, "_pose_of", lambda *a, **k: _pose(left if fit else None, None if fit else left))
    motion = _Motion()
    searched = ServoTiming(0.009, 1.0, motion.name, 0.24, 0.04, 30)
    timing, _, pose = report._refined_by_building(np.zeros(3), searched, motion, {}, Storage(40, 25, 10),
                                                  StorageFrame(), np.zeros(3),
                                                  ReportOptions(plots=False, pose_correction=pose_correction),
                                                  SensorErrorModel(), SQUARE, False)
    return timing, motion.applied, pose


@pytest.mark.parametrize("fit", [True, False], ids=["beside the drift's fit", "as logged"])
def test_that_the_search_s_delay_takes_what_the_floor_and_walls_still_show(monkeypatch, fit):
    """The search stops at its millisecond step (9 ms of 10 under the datasheet's noise); the floor and walls on the
    samples it re-timed measure the rest, which is added, whether or not it would move their points by more than
    their noise: the servo is re-timed anyway. The samples are re-timed by the sum."""
    timing, applied, pose = _refined(monkeypatch, _split(0.00097, 0.00006, 0.02), fit)
    assert math.isclose(timing.delay_s, 0.00997) and math.isclose(timing.refined_s, 0.00097)
    assert timing.gain == 1.0 and applied[-1] == (timing.delay_s, 1.0)
    assert pose is None  # made on samples the refinement re-timed again: not theirs


@pytest.mark.parametrize("left", [_split(0.0002, 0.0001, 0.01), _split(LAST_BUT_ONE_STEP_S + 0.001, 0.0001, 0.2), None],
                         ids=["not measured", "beyond the search's step before its last", "not seen"])
def test_that_the_search_s_delay_stands_where_the_floor_and_walls_do_not_measure_a_rest_within_its_step(monkeypatch,
                                                                                                         left):
    timing, applied, pose = _refined(monkeypatch, left)
    assert timing.delay_s == 0.009 and timing.refined_s is None and applied == [(0.009, 1.0)]
    assert pose is not None and pose.servo_delay is left  # made on the samples as re-timed: the first estimates' own


def test_that_without_the_pose_correction_the_search_s_delay_stands(monkeypatch):
    timing, applied, pose = _refined(monkeypatch, _split(0.00097, 0.00006, 0.02), pose_correction=False)
    assert timing.delay_s == 0.009 and timing.refined_s is None and applied == [(0.009, 1.0)] and pose is None
