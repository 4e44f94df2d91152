"""A mission against its rangefinder's range: what the sweep and the floor reach, from the geometry."""

import math

import numpy as np
import pytest

from firmware_py.core.sensor import LIDARLITE_V3, TFMINI_S
from firmware_py.core.storage import Storage
from firmware_py.core.waveform import named_waveform
from ground.report import LOW_COVERAGE_PCT
from sitl.missions.range_check import (
    FLOOR_WARN_PCT,
    beam_ranges_empty,
    check_range,
    floor_within_reach,
    range_coverage,
)
from sitl.missions.rectangle import Mission

WF = named_waveform("semi-triangular", 5.0, 0)
TFMINI_BAY = Mission(storage=Storage(30, 20, 10), p_traj=0.20, altitude_m=9.0)


def test_that_a_beam_meets_the_floor_below_and_the_near_wall_across():
    m = Mission(storage=Storage(30, 20, 10), p_traj=0.25, altitude_m=9.0)  # long legs 5 m from the walls
    r = beam_ranges_empty(m, 8.9, np.array([0.0, math.pi / 2, math.radians(30)]))
    assert np.allclose(r[:, 0], 8.9)  # straight down
    on_long_leg = np.isclose(r[:, 1], 5.0)  # level, to the wall on the right of the direction of flight
    assert on_long_leg.mean() > 0.4
    # At 30 deg the floor is 10.28 m away along the beam, 5.14 m across: beyond the long legs' wall 5 m
    # across (met at 5 / sin 30 = 10 m), short of the short legs' 7.5 m.
    floor_30 = 8.9 / math.cos(math.radians(30))
    assert np.all(np.isclose(r[:, 2], 10.0) | np.isclose(r[:, 2], floor_30))
    assert np.array_equal(np.isclose(r[:, 2], 10.0), on_long_leg)


def test_that_the_floor_reached_is_all_of_it_when_the_reach_spans_the_building():
    assert floor_within_reach(TFMINI_BAY, 40.0) == 1.0
    assert floor_within_reach(TFMINI_BAY, 0.0) < 0.01


def test_that_the_lidarlite_reaches_every_floor_and_wall_of_the_default_building():
    c = range_coverage(Mission(p_traj=0.05), LIDARLITE_V3.max_range_m, WF)
    assert c.floor_reach_pct == 100.0 and c.in_range_pct > 90.0
    assert check_range(Mission(p_traj=0.05), LIDARLITE_V3.max_range_m, WF) is None


def test_that_a_tfmini_at_the_lidarlites_height_is_refused_naming_its_reach():
    with pytest.raises(ValueError, match=r"mostly out of range: a 12 m rangefinder 11\.9 m above the floor reaches "
                                         r"1\.5 m"):
        check_range(Mission(p_traj=0.20), TFMINI_S.max_range_m, WF)


def test_that_the_tfmini_bay_is_reached_whole_and_legs_too_far_in_are_warned_about():
    c = range_coverage(TFMINI_BAY, TFMINI_S.max_range_m, WF)
    assert c.floor_reach_m == pytest.approx(math.sqrt(12.0 ** 2 - 8.9 ** 2))
    assert c.floor_reach_pct == 100.0 and check_range(TFMINI_BAY, TFMINI_S.max_range_m, WF) is None
    inner = Mission(storage=Storage(30, 20, 10), p_traj=0.30, altitude_m=9.0)  # the corners fall out of reach
    warning = check_range(inner, TFMINI_S.max_range_m, WF)
    assert warning is not None and "part of the floor is out of range" in warning


def test_that_the_floor_warning_level_is_the_ground_reports_coverage_warning():
    assert FLOOR_WARN_PCT == LOW_COVERAGE_PCT
