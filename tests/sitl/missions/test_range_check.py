"""A mission against its rangefinder's range: what the sweep and the floor reach, from the geometry."""

import math

import numpy as np
import pytest

from firmware_py.core.sensor import LIDARLITE_V3, TFMINI_S, Rangefinder, return_model_for
from firmware_py.core.sensor_noise import SensorNoise
from firmware_py.core.storage import Storage
from firmware_py.core.waveform import named_waveform
from ground.report import LOW_COVERAGE_PCT
from sitl.missions.range_check import (
    FLOOR_WARN_PCT,
    RangeLimit,
    beam_hits_empty,
    beam_ranges_empty,
    check_range,
    floor_within_reach,
    planning_limit,
    range_coverage,
)
from sitl.missions.rectangle import Mission
from sitl.runners.fly import FlyConfig, fly
from sitl.sensing.noise import dropout_probability

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
    with pytest.raises(ValueError, match=r"mostly out of range: planning range 12 m \(the Benewake TFmini-S's rated "
                                         r"range\): 11\.9 m above the floor the sensor reaches 1\.5 m"):
        check_range(Mission(p_traj=0.20), planning_limit(TFMINI_S, "none"), WF)


def test_that_the_tfmini_bay_is_reached_whole_and_legs_too_far_in_are_warned_about():
    c = range_coverage(TFMINI_BAY, TFMINI_S.max_range_m, WF)
    assert c.floor_reach_m == pytest.approx(math.sqrt(12.0 ** 2 - 8.9 ** 2))
    assert c.floor_reach_pct == 100.0 and check_range(TFMINI_BAY, TFMINI_S.max_range_m, WF) is None
    inner = Mission(storage=Storage(30, 20, 10), p_traj=0.30, altitude_m=9.0)  # the corners fall out of reach
    warning = check_range(inner, TFMINI_S.max_range_m, WF)
    assert warning is not None and "part of the floor is out of range" in warning


def test_that_the_floor_warning_level_is_the_ground_reports_coverage_warning():
    assert FLOOR_WARN_PCT == LOW_COVERAGE_PCT


# -- planning with the range at the surfaces' reflectance ------------------------------------------------

DATASHEET_TFMINI = planning_limit(TFMINI_S, "datasheet")


def test_that_ideal_sensing_plans_with_the_rated_range_and_the_datasheet_noise_with_the_return_model():
    for model in ("none", "appendix-a"):
        assert planning_limit(TFMINI_S, model).returns is None
        assert planning_limit(TFMINI_S, model).normal_reach_m == TFMINI_S.max_range_m
    returns = return_model_for(TFMINI_S)
    assert DATASHEET_TFMINI.returns == returns
    # The certain-echo range: where the no-return ramp starts, below the effective range on 30 % surfaces.
    assert DATASHEET_TFMINI.normal_reach_m == pytest.approx((1 - returns.dropout_ramp_rel)
                                                            * returns.effective_range_m(TFMINI_S.max_range_m))
    assert DATASHEET_TFMINI.normal_reach_m == pytest.approx(0.9 * 12 * math.sqrt(0.3 / 0.9))  # 6.2 m
    with pytest.raises(ValueError, match="unknown sensor noise"):
        planning_limit(TFMINI_S, "loud")


def test_that_the_planned_reach_is_where_the_simulated_sensor_starts_to_lose_echoes():
    """At each incidence, the planning's reach is the range at which the datasheet noise's no-return
    probability leaves 0: the check and the simulator agree on what is reached."""
    cos_i = np.array([1.0, 0.8, 0.5, 0.2])
    reach = DATASHEET_TFMINI.reach_m(cos_i)
    noise = SensorNoise.of("datasheet", TFMINI_S)
    assert np.all(dropout_probability(reach * 0.999, cos_i, TFMINI_S, noise.returns) == 0.0)
    assert np.all(dropout_probability(reach * 1.02, cos_i, TFMINI_S, noise.returns) > 0.0)


def test_that_the_bare_floors_reach_is_where_the_beams_range_meets_its_reach_at_its_incidence():
    for h in (2.0, 4.9, 6.0):
        across = DATASHEET_TFMINI.floor_reach_m(h)
        gamma = math.atan2(across, h)  # the beam to the floor's edge: range h / cos, incidence gamma
        assert h / math.cos(gamma) == pytest.approx(float(DATASHEET_TFMINI.reach_m(math.cos(gamma))))
    assert DATASHEET_TFMINI.floor_reach_m(DATASHEET_TFMINI.normal_reach_m + 0.01) == 0.0  # not even below
    heights = np.linspace(0.1, 6.2, 611)
    widest = heights[np.argmax([DATASHEET_TFMINI.floor_reach_m(h) for h in heights])]
    assert widest == pytest.approx(DATASHEET_TFMINI.widest_floor_height_m, abs=0.011)
    assert RangeLimit(12.0).floor_reach_m(8.9) == pytest.approx(math.sqrt(12 ** 2 - 8.9 ** 2))


def test_that_a_wall_met_obliquely_reports_its_incidence():
    m = Mission(storage=Storage(30, 20, 10), p_traj=0.25, altitude_m=9.0)
    _r, cos_i = beam_hits_empty(m, 8.9, np.array([0.0, math.pi / 2]))
    assert np.allclose(cos_i[:, 0], 1.0)  # the floor straight below
    assert np.allclose(cos_i[:, 1], 1.0)  # a wall met level, square across the leg
    # At 30 deg the long legs' beam meets the wall 5 m across (at 10 m, incidence 60 deg), the short legs'
    # the floor (at 10.28 m, incidence 30 deg).
    r30, c30 = beam_hits_empty(m, 8.9, np.array([math.radians(30)]))
    on_wall = np.isclose(r30[:, 0], 10.0)
    assert on_wall.any() and (~on_wall).any()
    assert np.allclose(c30[on_wall, 0], 0.5) and np.allclose(c30[~on_wall, 0], math.cos(math.radians(30)))


def test_that_the_tfmini_at_9_m_over_30_pct_surfaces_is_refused_naming_what_is_out_of_reach_and_the_fix():
    with pytest.raises(ValueError) as err:
        check_range(TFMINI_BAY, TFMINI_S.max_range_m, WF, returns=return_model_for(TFMINI_S))
    msg = str(err.value)
    assert "\n" not in msg
    assert "planning range 6.2 m" in msg and "30 % reflective" in msg
    assert "out of reach: all of the floor, even straight below" in msg
    assert "fly lower (the floor below is reached from at most 6.2 m above it" in msg


def test_that_the_fly_runner_refuses_the_9_m_tfmini_flight_with_datasheet_noise_before_flying(tmp_path):
    cfg = FlyConfig(mission=TFMINI_BAY, stockpile="1", payload="firmware", rangefinder=Rangefinder.TFMINI,
                    sensor_noise="datasheet")
    with pytest.raises(ValueError, match=r"mostly out of range: planning range 6\.2 m"):
        fly(cfg, tmp_path / "run", progress=lambda _m: None)
    assert not (tmp_path / "run" / "truth.json").exists()


def test_that_the_low_tfmini_mission_is_flown_with_the_floor_along_the_walls_in_reach():
    """5 m, P_traj 10 % (the campaign's mission): the legs run within the floor's reach of the walls, so
    the bare floor is reached along them; the middle of an empty bay is not, which the warning says."""
    low = Mission(storage=Storage(30, 20, 10), p_traj=0.10, altitude_m=5.0)
    c = range_coverage(low, DATASHEET_TFMINI, WF)
    assert c.floor_reach_m >= 0.10 * 30  # the end walls' legs 3 m in: the floor between them reached
    warning = check_range(low, DATASHEET_TFMINI, WF)
    assert warning is not None and "out of reach: the floor beyond +-" in warning
    assert "P_traj <= 10 %" in warning and "the walls" not in c.out_of_reach()
    higher = Mission(storage=Storage(30, 20, 10), p_traj=0.10, altitude_m=5.5)
    assert range_coverage(higher, DATASHEET_TFMINI, WF).floor_reach_m < 0.10 * 30  # 5.5 m: reach too short


def test_that_the_remedy_gives_a_p_traj_band_when_one_reaches_all_the_bare_floor():
    m = Mission(p_traj=0.05)  # the LIDAR-Lite's own mission, 60 x 40 m from 12 m
    warning = check_range(m, planning_limit(LIDARLITE_V3, "datasheet"), WF)
    assert warning is not None and "or choose P_traj 14-24 %" in warning
    assert check_range(Mission(p_traj=0.20), planning_limit(LIDARLITE_V3, "datasheet"), WF) is None
