"""ground.pose_source_check: the report names the autopilot's pose source and warns where it biases the volume
and nothing corrected it."""

import numpy as np

from firmware_py.core.pose_source import HEADER_KEY
from ground.pose_correction import PoseCorrection, not_applied
from ground.pose_source_check import NOT_STATED, autopilot_params, pose_source_line, pose_source_warnings
from ground.rangefinder_height import RangefinderShare

GNSS = {"AHRS_EKF_TYPE": 3.0, "EK3_SRC1_POSXY": 3.0, "EK3_SRC1_VELXY": 3.0, "EK3_SRC1_POSZ": 1.0,
        "EK3_SRC1_YAW": 1.0, "EK3_RNG_USE_HGT": -1.0}
FLOW = {**GNSS, "EK3_SRC1_POSXY": 0.0, "EK3_SRC1_VELXY": 5.0, "EK3_RNG_USE_HGT": 70.0}


def _applied(height_sigma_m: float | None) -> PoseCorrection:
    k = np.array([0.0, 3.0])
    return PoseCorrection(k, np.zeros((2, 4)), np.ones((2, 4), dtype=bool), True, height_sigma_m=height_sigma_m)


def test_that_a_rangefinder_height_left_uncorrected_is_warned_about_with_the_parameter_and_why():
    header = {HEADER_KEY: FLOW}
    [w] = pose_source_warnings(header, not_applied("too small to matter"), correction_on=True)
    assert "EK3_RNG_USE_HGT = 70" in w and "(too small to matter)" in w and "possibly low" in w
    off = pose_source_warnings(header, None, correction_on=False)
    assert len(off) == 2 and "--no-pose-correction" in off[0]
    assert off[1].startswith("the autopilot's position was optical flow velocity, integrated, which drifts")


def test_that_a_rangefinder_as_the_height_source_is_named_by_its_source_parameter():
    [w] = pose_source_warnings({HEADER_KEY: {**GNSS, "EK3_SRC1_POSZ": 2.0}}, _applied(None), correction_on=True)
    assert "as its height source (EK3_SRC1_POSZ = 2)" in w  # a horizontal-only correction leaves the height


def test_that_a_corrected_height_or_a_gnss_pose_needs_no_warning():
    assert pose_source_warnings({HEADER_KEY: FLOW}, _applied(0.01), correction_on=True) == []
    assert pose_source_warnings({HEADER_KEY: GNSS}, None, correction_on=False) == []


def test_that_a_log_without_the_record_says_not_stated_and_warns_of_nothing():
    assert pose_source_line({}) == NOT_STATED and autopilot_params({}) is None
    assert pose_source_warnings({}, None, correction_on=False) == []
    assert pose_source_warnings({HEADER_KEY: {"EK3_SRC1_POSZ": "two"}}, None, correction_on=False) == []


def test_that_a_log_without_the_record_says_what_the_share_measured_all_the_same_found():
    found = RangefinderShare(0.25, 0.03, 900, True, source_stated=False)
    line = pose_source_line({}, found)
    assert line.startswith(NOT_STATED) and "measured all the same: 0.25 ± 0.03, taken out" in line
    none = RangefinderShare(0.01, 0.02, 900, False, "not significant (0.01 ± 0.02)", source_stated=False)
    assert pose_source_line({}, none).endswith("none taken out (not significant (0.01 ± 0.02))")
    stated = RangefinderShare(0.25, 0.03, 900, True)  # a record that said so: its own line and warning say it
    assert pose_source_line({HEADER_KEY: FLOW}, stated) == pose_source_line({HEADER_KEY: FLOW})


def test_that_a_share_the_crossings_could_not_measure_is_said_with_what_corrected_the_height_instead():
    why = "not significant (0.21 ± 0.07)"
    [note] = pose_source_warnings({HEADER_KEY: FLOW}, _applied(0.01), correction_on=True, rangefinder_reason=why)
    assert note.startswith("the autopilot's EKF took its height from the downward rangefinder")
    assert f"to take out: {why}; the height was corrected from the floor and walls instead" in note
    [warning] = pose_source_warnings({HEADER_KEY: FLOW}, not_applied("too small to matter"), correction_on=True,
                                     rangefinder_reason=why)
    # neither repair: one warning that names both reasons
    assert "possibly low" in warning and f"the rangefinder's share to take out: {why}, and the 90 %" in warning
    assert pose_source_warnings({HEADER_KEY: FLOW}, _applied(0.01), correction_on=True, rangefinder_applied=True) == []
    assert pose_source_warnings({HEADER_KEY: GNSS}, _applied(0.01), correction_on=True, rangefinder_reason=why) == []
