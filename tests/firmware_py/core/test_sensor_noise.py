"""The header's sensor_noise record: which model flew and its parameters, round trip, and what the ground reads."""

import json
import math

import pytest

from firmware_py.core.frames import StorageFrame
from firmware_py.core.header import LogHeader, build_log_header
from firmware_py.core.sensor import LIDARLITE_V3, TFMINI_S, RangefinderSpec
from firmware_py.core.sensor_noise import (
    HEADER_KEY,
    POSE_STREAM_HZ,
    SensorNoise,
    SensorNoiseModel,
    describe_record,
    stated_pose_draw,
    stated_position_sigma_m,
    stated_range_sigma,
)
from firmware_py.core.storage import Storage
from firmware_py.core.waveform import named_waveform


def header_with(record):
    return build_log_header(source="sitl/test", sensor=LIDARLITE_V3.to_dict(), lever_arm_body_m=(0, 0, 0.1),
                            waveform_name="semi-triangular", waveform=named_waveform("semi-triangular"),
                            initial_position=0, storage=Storage(), frame=StorageFrame(),
                            extra={} if record is None else {HEADER_KEY: record})


@pytest.mark.parametrize("spec", [LIDARLITE_V3, TFMINI_S])
@pytest.mark.parametrize("model", [SensorNoiseModel.DATASHEET, SensorNoiseModel.APPENDIX_A])
def test_that_the_record_survives_the_log_header_round_trip(spec, model):
    noise = SensorNoise.of(model, spec)
    stored = json.loads(json.dumps(header_with(noise.record())))
    back = LogHeader.from_dict(stored).extra[HEADER_KEY]
    assert back == noise.record()
    assert SensorNoise.from_record(back, spec) == noise
    assert back["model"] == model.value and back["rangefinder"] == spec.model


def test_that_no_noise_writes_no_record_so_the_header_is_what_it_always_was():
    assert SensorNoise.of("none", LIDARLITE_V3).record() is None
    assert HEADER_KEY not in header_with(None)
    assert SensorNoise.from_record(None, LIDARLITE_V3).model is SensorNoiseModel.NONE


def test_that_the_datasheet_record_states_the_specs_error_model_and_the_return_model():
    rec = SensorNoise.of("datasheet", TFMINI_S).record()
    assert (rec["range_sigma_m"], rec["range_sigma_rel"], rec["resolution_m"]) == (0.06, 0.01, 0.01)
    assert rec["reference_reflectance"] == 0.9 and rec["max_range_m"] == 12.0 and rec["bias_m"] == 0.0
    assert "12 m" in describe_record(rec) and "datasheet" in describe_record(rec)


def test_that_appendix_a_states_the_papers_sigmas():
    rec = SensorNoise.of("appendix-a", LIDARLITE_V3).record()
    assert rec["range_sigma_m"] == 0.025 and rec["position_sigma_m"] == 0.113
    assert math.degrees(rec["servo_sigma_rad"]) == pytest.approx(1.0)
    assert math.degrees(rec["attitude_sigma_rad"]) == pytest.approx(0.143)
    assert stated_position_sigma_m({HEADER_KEY: rec}) == 0.113
    assert stated_range_sigma({HEADER_KEY: rec}) == (0.025, 0.0)
    assert "servo angle 1 deg" in describe_record(rec)


def test_that_a_sensor_without_a_datasheet_return_model_is_refused_by_name():
    odd = RangefinderSpec("Acme Ranger", 100.0, 20.0, 0.01, 0.02, 0.0, 0.01)
    with pytest.raises(ValueError, match="Acme Ranger"):
        SensorNoise.of("datasheet", odd)
    assert SensorNoise.of("appendix-a", odd).active  # the paper's model does not depend on the sensor


@pytest.mark.parametrize("record,match", [
    ("datasheet", "JSON object"),
    ({"model": "gaussian"}, "sensor_noise.model"),
    ({"model": "appendix-a", "range_sigma_m": 0.025}, "lacks"),
    ({**SensorNoise.of("appendix-a", LIDARLITE_V3).record(), "position_sigma_m": -1.0}, "position_sigma_m"),
    ({**SensorNoise.of("datasheet", LIDARLITE_V3).record(), "target_reflectance": 2.0}, "target_reflectance"),
])
def test_that_a_bad_record_is_refused_naming_what_is_wrong(record, match):
    with pytest.raises(ValueError, match=match):
        SensorNoise.from_record(record, LIDARLITE_V3)


def test_that_a_stated_sigma_that_is_not_a_number_is_refused():
    with pytest.raises(ValueError, match="position_sigma_m"):
        stated_position_sigma_m({HEADER_KEY: {"model": "appendix-a", "position_sigma_m": "big"}})
    assert stated_position_sigma_m({}) == 0.0 and stated_range_sigma({}) == (0.0, 0.0)


def test_that_the_pose_draw_is_the_records_position_sigma_at_its_message_rate():
    record = SensorNoise.of(SensorNoiseModel.APPENDIX_A, LIDARLITE_V3).record()
    assert stated_pose_draw(header_with(record)) == (0.113, record["pose_stream_hz"])
    assert stated_pose_draw(header_with(None)) == (0.0, POSE_STREAM_HZ)
    assert stated_pose_draw({HEADER_KEY: {"model": "appendix-a", "position_sigma_m": 0.1}}) == (0.1, POSE_STREAM_HZ)
    with pytest.raises(ValueError, match="pose_stream_hz"):
        stated_pose_draw({HEADER_KEY: {"model": "appendix-a", "pose_stream_hz": -5}})
