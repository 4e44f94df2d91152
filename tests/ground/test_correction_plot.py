"""ground.correction_plot: the report draws what it added to the logged pose over time, the rangefinder's lift in the
height, and shades where the floor and walls did not set it."""

import math
from types import SimpleNamespace

import numpy as np
import pytest

from ground.correction_plot import FIGURE_NAME, correction_figure, correction_series
from ground.figure_jobs import draw
from ground.pose_correction import PoseCorrection
from ground.rangefinder_height import RangefinderShare
from ground.report_figures import correction_figure_jobs


def _pose(applied: bool = True) -> PoseCorrection:
    knots = np.array([0.0, 10.0, 20.0, 30.0])
    values = np.array([[0.0, 0.0, 0.0, 0.0], [0.1, -0.2, 0.05, math.radians(0.5)],
                       [0.2, -0.3, 0.1, math.radians(1.0)], [0.3, -0.3, 0.1, math.radians(1.0)]])
    constrained = np.ones((4, 4), dtype=bool)
    constrained[1:3, 2] = False  # the height between 10 s and 20 s from the prior alone
    return PoseCorrection(knots, values, constrained, applied)


def _lift(applied: bool = True) -> RangefinderShare:
    t = tuple(float(v) for v in np.arange(0.0, 30.05, 0.1))
    lift = tuple(0.5 if 12.0 <= v <= 18.0 else 0.0 for v in t)
    return RangefinderShare(0.25, 0.01, 400, applied, None, (0.1, 0.5), t, lift)


def test_that_the_height_drawn_is_the_pose_correction_plus_the_rangefinder_lift():
    s = correction_series(_pose(), _lift())
    at15 = np.argmin(np.abs(s.t_s - 15.0))
    assert s.shift_w_m[at15, 2] == pytest.approx(0.075 + 0.5, abs=1e-9)  # the pose's (between knots) and the lift
    assert s.lift_m[at15] == pytest.approx(0.5)
    assert s.shift_w_m[at15, 0] == pytest.approx(0.15, abs=1e-9)  # linear between the knots
    assert s.heading_deg[-1] == pytest.approx(1.0)  # degrees at the figure, radians inside
    assert set(s.t_s) >= {0.0, 10.0, 20.0, 30.0}  # the knots' corners are on the grid
    assert s.free_z_s == ((10.0, 20.0),) and s.free_heading_s == ()


def test_that_each_correction_is_drawn_alone_and_nothing_is_drawn_when_none_was_applied():
    assert correction_series(None, None) is None
    assert correction_series(_pose(applied=False), _lift(applied=False)) is None
    pose_only = correction_series(_pose(), None)
    assert pose_only.lift_m is None and list(pose_only.t_s) == [0.0, 10.0, 20.0, 30.0]
    lift_only = correction_series(None, _lift())
    assert lift_only.shift_w_m[:, :2].max() == 0.0 and lift_only.shift_w_m[:, 2].max() == pytest.approx(0.5)
    assert lift_only.free_z_s == ()
    # a lever arm placed in place of a drift: the trajectory is not what moved, so no figure of it
    lever = PoseCorrection(np.array([0.0, 10.0]), np.zeros((2, 4)), np.zeros((2, 4), dtype=bool), True,
                           lever_change_m=(0.3, 0.0))
    assert correction_series(lever, None) is None


def test_that_the_figure_shows_position_and_heading_the_lift_dashed_and_the_free_stretch_shaded():
    fig = correction_figure(correction_series(_pose(), _lift()))
    top, bottom = fig.axes
    labels = [t.get_text() for t in top.get_legend().get_texts()]
    assert labels[:3] == ["x (along the length)", "y (along the width)", "height"]
    assert any("rangefinder" in t for t in labels) and any("interpolated" in t for t in labels)
    dashed = [ln for ln in top.get_lines() if ln.get_linestyle() == "--"]
    assert len(dashed) == 1 and max(dashed[0].get_ydata()) == pytest.approx(0.5)
    assert len(top.patches) == 1  # the one stretch the floor did not set
    assert "heading" in bottom.get_ylabel() and "[deg]" in bottom.get_ylabel()
    assert bottom.get_legend() is None  # no heading was left free here: nothing shaded, no key


def test_that_a_heading_left_free_is_shaded_with_its_own_key():
    # the heading panel's shading had no key: only the caption said what it meant
    pose = _pose()
    pose.constrained[1:3, 3] = False  # the heading between 10 s and 20 s too
    fig = correction_figure(correction_series(pose, None))
    _, bottom = fig.axes
    assert [t.get_text() for t in bottom.get_legend().get_texts()] == ["heading not set by the walls (interpolated)"]


def test_that_a_report_writes_the_figure_only_when_it_corrected_the_trajectory(tmp_path):
    drifting = SimpleNamespace(pose=_pose(), rangefinder=None)
    written = draw(correction_figure_jobs(drifting, tmp_path))
    assert written == {FIGURE_NAME: tmp_path / f"{FIGURE_NAME}.png"} and written[FIGURE_NAME].stat().st_size > 1000
    assert correction_figure_jobs(SimpleNamespace(pose=None, rangefinder=None), tmp_path / "none") == []
