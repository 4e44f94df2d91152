"""ground.rangefinder_height: a logged height that followed the pile below (a rangefinder height source) is measured
from the pile seen at different ground heights below the vehicle, without a floor, and taken out; a height that
did not follow it is left alone."""

import json

import numpy as np
import pytest

from firmware_py.core.frames import SQUARE
from firmware_py.core.samplelog import SampleFlags
from ground.rangefinder_height import _Crossings, _lowpass, estimate_share
from tests.ground.test_pose_correction import FRAME, LEVER, PERIOD_S, PILE, STORAGE, _track, flight

OVER_THE_PILE = [(12.0, 17.0), (48.0, 17.0), (48.0, 23.0), (12.0, 23.0)]
"""A loop whose long legs cross the block pile (x 22-38 m, y 14-26 m, 3 m tall): the ground below steps 0 -> 3 m."""


def _below_true(t: np.ndarray) -> np.ndarray:
    xy, _ = _track(t, OVER_THE_PILE)
    inside = (xy[:, 0] >= PILE[0][0]) & (xy[:, 0] <= PILE[1][0]) & (xy[:, 1] >= PILE[0][1]) & (xy[:, 1] <= PILE[1][1])
    return np.where(inside, PILE[1][2], 0.0)


def _following(share: float):
    def err(t: np.ndarray) -> np.ndarray:
        out = np.zeros((len(t), 4))
        out[:, 2] = -share * _lowpass(_below_true(t), t, 1.0)  # logged low by a share of the ground below
        return out
    return err


@pytest.fixture(scope="module")
def followed():
    samples, err = flight(_following(0.4), corners=OVER_THE_PILE)
    share, placed = estimate_share(samples, LEVER, FRAME, STORAGE, 2 * PERIOD_S)
    return samples, err, share, placed


def test_that_a_height_that_followed_the_pile_is_measured_and_taken_out(followed):
    samples, err, share, placed = followed
    assert share.applied and share.share == pytest.approx(0.4, abs=0.05) and share.sigma < 0.05
    logged_up = FRAME.ned_to_w(np.column_stack([samples["x_m"], samples["y_m"], samples["z_m"]]))[:, 2]
    placed_up = FRAME.ned_to_w(np.column_stack([placed["x_m"], placed["y_m"], placed["z_m"]]))[:, 2]
    true_up = logged_up - err[:, 2]
    before, after = np.abs(logged_up - true_up), np.abs(placed_up - true_up)
    assert after.mean() < 0.25 * before.mean()  # the lift put back most of what the ground below took


def test_that_the_report_says_how_much_it_raised_the_height_over_time(followed):
    samples, _, share, placed = followed
    logged_up = FRAME.ned_to_w(np.column_stack([samples["x_m"], samples["y_m"], samples["z_m"]]))[:, 2]
    placed_up = FRAME.ned_to_w(np.column_stack([placed["x_m"], placed["y_m"], placed["z_m"]]))[:, 2]
    raised = placed_up - logged_up
    assert raised.max() > 0.5  # the pile is 3 m tall: a lift worth following
    off = share.lift_at(samples["t_s"]) - raised  # what a reader re-places a trajectory with
    assert np.sqrt(np.mean(off ** 2)) < 0.01 and np.abs(off).max() < 0.05
    record = json.loads(json.dumps(share.as_dict(), allow_nan=False))
    assert np.interp(samples["t_s"], record["lift_t_s"], record["lift_at_t_m"]) == pytest.approx(
        share.lift_at(samples["t_s"]), abs=1e-3)


def test_that_a_height_that_did_not_follow_the_pile_is_left_alone():
    samples, _ = flight(None, corners=OVER_THE_PILE)
    share, placed = estimate_share(samples, LEVER, FRAME, STORAGE, 2 * PERIOD_S)
    assert not share.applied and "not significant" in share.reason and placed is samples
    assert not share.lift_at(samples["t_s"]).any() and share.as_dict()["lift_t_s"] == []


def test_that_a_flight_that_never_sees_a_cell_at_two_ground_heights_says_so():
    samples, _ = flight(None)  # the default loop runs around the pile: the ground below is always the floor
    share, placed = estimate_share(samples, LEVER, FRAME, STORAGE, 2 * PERIOD_S)
    assert not share.applied and placed is samples


def test_that_the_crossings_fit_is_the_slope_of_the_cells_heights_on_the_ground_below():
    rng = np.random.default_rng(1)
    t = np.repeat(np.arange(8.0), 50) * 10.0  # eight passes, 10 s apart, 50 points each in one cell
    below = np.repeat(rng.uniform(0, 5, 8), 50)
    z = 2.0 - 0.3 * below + rng.normal(0, 0.01, len(t))
    points = np.column_stack([np.full(len(t), 5.2), np.full(len(t), 7.7), z])
    w, sigma, misfit = _Crossings.of(points, t, 3.0).fit(below)
    assert w == pytest.approx(0.3, abs=0.01) and sigma < 0.01 and misfit < 0.01


def test_that_a_log_with_too_few_points_says_so_and_changes_nothing():
    samples, _ = flight(None, corners=OVER_THE_PILE)
    few = samples[:50]
    share, placed = estimate_share(few, LEVER, FRAME, STORAGE, 2 * PERIOD_S)
    assert not share.applied and "too few" in share.reason and placed is few


def test_that_samples_logged_without_a_pose_neither_break_the_share_nor_spread_into_it():
    samples, _ = flight(_following(0.4), corners=OVER_THE_PILE)
    gap = slice(len(samples) // 3, len(samples) // 3 + 500)  # a second of samples the payload could not pose
    samples["x_m"][gap] = samples["y_m"][gap] = samples["z_m"][gap] = np.nan
    samples["flags"][gap] |= int(SampleFlags.NO_POSE)
    share, placed = estimate_share(samples, LEVER, FRAME, STORAGE, 2 * PERIOD_S)
    assert share.applied and share.share == pytest.approx(0.4, abs=0.05)
    posed = np.isfinite(samples["z_m"])
    assert np.isfinite(placed["z_m"][posed]).all() and np.isnan(placed["z_m"][~posed]).all()


def _passes_sharing_an_error(seed: int, w: float = 0.3):
    """Sixty passes 10 s apart over a 8 x 5 grid of cells, each pass at its own ground height below and with an error
    all its cells share (0.05 m: a drift the 30 s knots cannot follow), each cell's height low by w times it."""
    rng = np.random.default_rng(seed)
    points, times, below = [], [], []
    for k in range(60):
        b, shared = rng.uniform(0, 5), rng.normal(0, 0.05)
        for c in rng.choice(40, 20, replace=False):
            z = 2.0 - w * b + shared + rng.normal(0, 0.01, 5)
            points.append(np.column_stack([np.full(5, c % 8 + 0.5), np.full(5, c // 8 + 0.5), z]))
            times.append(10.0 * k + rng.uniform(0, 2, 5))
            below.append(np.full(5, b))
    return _Crossings.of(np.vstack(points), np.concatenate(times), 3.0), np.concatenate(below)


def test_that_the_share_s_error_holds_what_a_pass_shares_across_its_cells():
    """The cells' error alone takes each cell as an independent draw: with an error shared by a pass's cells it put
    the true share five of its errors away; the jackknife over stretches of the flight covers it."""
    z_cells, z_blocks = [], []
    for seed in range(12):
        crossings, below = _passes_sharing_an_error(seed)
        w, sigma, _ = crossings.fit(below)
        z_cells.append(abs(w - 0.3) / sigma)
        z_blocks.append(abs(w - 0.3) / crossings.block_sigma(below))
    assert np.median(z_cells) > 3.0  # overconfident: why the block error is there
    assert np.median(z_blocks) < 1.5 and max(z_blocks) < 3.5


BARO = {"AHRS_EKF_TYPE": 3, "EK3_SRC1_POSXY": 0, "EK3_SRC1_VELXY": 5, "EK3_SRC1_POSZ": 1, "EK3_RNG_USE_HGT": -1}


def _report_share(samples, record):
    from ground.report import ReportOptions, _rangefinder_share

    header = {"servo": {"frequency_hz": 1.0 / PERIOD_S}}
    if record is not None:
        header["autopilot_params"] = record
    return _rangefinder_share(samples, header, STORAGE, FRAME, LEVER, ReportOptions(plots=False), SQUARE)


def test_that_the_report_measures_the_share_when_the_log_does_not_say_where_the_height_came_from(followed):
    # An older payload, or an autopilot that did not answer: the crossings decide, and the report says the log
    # did not say (a `flow` flight over a pile that hid its floor read 23-31 % low without this)
    samples = followed[0]
    for record in (None, {"EK3_SRC1_VELXY": 5}):  # no record; parameters that name no EKF3 sources
        placed, share = _report_share(samples, record)
        assert share.applied and share.share == pytest.approx(0.4, abs=0.05) and not share.source_stated
        assert placed is not samples and "does not say" in share.describe()
        assert share.as_dict()["source_stated"] is False


def test_that_the_report_trusts_a_record_that_names_the_height_s_source(followed):
    samples = followed[0]
    placed, share = _report_share(samples, BARO)  # the barometer: nothing to measure
    assert share is None and placed is samples
    placed, share = _report_share(samples, {**BARO, "EK3_SRC1_POSZ": 2})  # the rangefinder, said so
    assert share.applied and share.source_stated and "does not say" not in share.describe()


def test_that_an_unstated_height_that_did_not_follow_the_pile_is_left_alone():
    samples, _ = flight(None, corners=OVER_THE_PILE)
    placed, share = _report_share(samples, None)
    assert not share.applied and placed is samples
