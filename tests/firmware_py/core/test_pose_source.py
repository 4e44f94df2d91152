"""The autopilot's pose sources, read back from the header's EKF3 parameters."""

import math

import pytest

from firmware_py.core.pose_source import HEADER_KEY, HeightSource, HorizontalSource, PoseSource

GNSS = {"AHRS_EKF_TYPE": 3.0, "EK3_SRC1_POSXY": 3.0, "EK3_SRC1_VELXY": 3.0, "EK3_SRC1_POSZ": 1.0,
        "EK3_SRC1_YAW": 1.0, "EK3_RNG_USE_HGT": -1.0}


def test_that_ardupilot_s_defaults_read_as_gnss_and_barometer_and_neither_drifts_nor_follows_the_pile():
    s = PoseSource.from_header({HEADER_KEY: GNSS})
    assert (s.position, s.velocity, s.height) == (HorizontalSource.GPS, HorizontalSource.GPS, HeightSource.BARO)
    assert s.known and not s.horizontal_drifts and not s.height_from_rangefinder
    assert s.describe() == "position GNSS; height barometer (ArduPilot EKF3, source set 1)"


def test_that_optical_flow_with_the_rangefinder_as_height_source_drifts_and_follows_the_pile():
    s = PoseSource.from_params({**GNSS, "EK3_SRC1_POSXY": 0.0, "EK3_SRC1_VELXY": 5.0, "EK3_SRC1_POSZ": 2.0})
    assert s.horizontal_drifts and s.height_from_rangefinder
    assert s.describe() == "position optical flow velocity, integrated; height downward rangefinder " \
                           "(ArduPilot EKF3, source set 1)"


def test_that_external_navigation_is_not_called_drifting_as_motion_capture_is_external_navigation_too():
    s = PoseSource.from_params({**GNSS, "EK3_SRC1_POSXY": 6.0, "EK3_SRC1_VELXY": 6.0})
    assert not s.horizontal_drifts and s.position is HorizontalSource.EXTERNAL_NAV


@pytest.mark.parametrize("header", [{}, {HEADER_KEY: {}}, {HEADER_KEY: "GPS"}, {HEADER_KEY: None}])
def test_that_a_log_without_the_record_has_no_pose_source(header):
    assert PoseSource.from_header(header) is None


@pytest.mark.parametrize("bad", [math.nan, math.inf, "3", True, None, 99.0, 2.5e9, 10**400, [2]])
def test_that_a_value_that_is_no_known_code_is_not_stated_rather_than_guessed(bad):
    s = PoseSource.from_params({**GNSS, "EK3_SRC1_POSZ": bad})
    assert s.height is None and not s.known
    assert s.describe() == "not stated by the autopilot"


def test_that_a_huge_integer_anywhere_is_no_number_rather_than_an_overflow():
    s = PoseSource.from_params({"AHRS_EKF_TYPE": 10**400, "EK3_SRC1_POSZ": 10**400, "EK3_RNG_USE_HGT": 10**400})
    assert (s.ekf_type, s.height, s.rangefinder_height_pct) == (None, None, None)


def test_that_another_ekf_says_its_sources_are_not_read():
    s = PoseSource.from_params({"AHRS_EKF_TYPE": 2.0})
    assert not s.known and "AHRS_EKF_TYPE 2" in s.describe()


def test_that_the_setting_that_makes_the_rangefinder_the_height_source_is_named_the_source_first():
    assert PoseSource.from_params(GNSS).rangefinder_height_setting is None
    switched = PoseSource.from_params({**GNSS, "EK3_RNG_USE_HGT": 70.0})
    assert switched.rangefinder_height_setting == "EK3_RNG_USE_HGT = 70"
    both = PoseSource.from_params({**GNSS, "EK3_SRC1_POSZ": 2.0, "EK3_RNG_USE_HGT": 70.0})
    assert both.rangefinder_height_setting == "EK3_SRC1_POSZ = 2"  # the source itself, whatever the switch says
