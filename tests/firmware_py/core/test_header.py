"""The sample-log header: one builder for the SITL and the payload, read by the ground station."""

from __future__ import annotations

import json
import math
from dataclasses import asdict

import pytest

from firmware_py.app import PayloadConfig
from firmware_py.core.frames import StorageFrame
from firmware_py.core.header import LogHeader, ServoDrive, build_log_header, sensor_spec
from firmware_py.core.samplelog import SampleLogWriter, read_samplelog, rewritable_header
from firmware_py.core.sensor import LIDARLITE_V3, SENSOR_KEYS
from firmware_py.core.servo_model import ServoCalibration
from firmware_py.core.site import Site
from firmware_py.core.storage import Storage
from firmware_py.core.waveform import named_waveform

STANDARD_KEYS = ["software", "created_utc", "source", "sensor", "lever_arm_body_m", "servo", "mission_id",
                 "mission", "storage", "storage_frame"]


def header(**kw):
    wf = named_waveform("sinusoidal", 4.0, 3)
    base = {"source": "payload", "sensor": sensor_spec(500.0), "lever_arm_body_m": (0.0, 0.0, 0.1),
            "waveform_name": "sinusoidal", "waveform": wf, "initial_position": 3, "storage": Storage(),
            "frame": StorageFrame((1.0, 2.0, 0.0), 0.5), "created_utc": "2025-01-01T00:00:00+00:00"}
    return build_log_header(**{**base, **kw})


def test_that_the_sensor_dict_is_the_lidarlite_v3_spec_in_header_key_order():
    assert tuple(LIDARLITE_V3.to_dict()) == SENSOR_KEYS
    assert tuple(sensor_spec(500.0)) == SENSOR_KEYS
    assert sensor_spec(500.0) == LIDARLITE_V3.to_dict()  # the datasheet defaults agree too


def test_that_the_header_has_the_standard_keys_in_order_with_the_servo_waveform():
    h = header()
    assert list(h) == STANDARD_KEYS
    assert h["source"] == "payload" and h["software"].startswith("pilescan ")
    assert h["servo"] == {"waveform": "sinusoidal", "shape_c": 0.0, "frequency_hz": pytest.approx(4.0 / math.pi**2),
                          "amplitude_rad": math.pi / 2, "phase_rad": pytest.approx(math.pi * 3.5 / 10),
                          "direction": 1, "initial_position": 3}
    assert h["storage_frame"] == {"origin_ned_m": [1.0, 2.0, 0.0], "heading_rad": 0.5}
    assert h["mission_id"] is None and h["mission"] is None


def test_that_the_sitl_log_header_is_built_by_the_same_function_with_its_values():
    pytest.importorskip("sitl", reason="the simulator (sitl/): not in the payload-only install")
    from sitl.runners.fly import FlyConfig, log_header

    cfg = FlyConfig()
    h = log_header(cfg, cfg.servo_waveform())
    # a simulated flight always knows where its building stands, and what its autopilot's EKF took the pose from
    assert list(h) == [*STANDARD_KEYS, "site", "autopilot_params"]
    assert h["site"] == cfg.site.to_dict()
    assert h["source"] == "sitl/jsbsim" and h["sensor"] == cfg.lidar.to_dict()
    assert h["mission_id"] == cfg.mission.mission_id and h["mission"] == cfg.mission.to_dict()
    assert h["storage"] == cfg.mission.storage.to_dict() and h["lever_arm_body_m"] == [0.0, 0.0, 0.10]


def test_that_the_ground_station_reads_the_payload_header(tmp_path):
    pytest.importorskip("ground", reason="the ground station (ground/): not in the payload-only install")
    from ground.pointcloud import SensorErrorModel
    from ground.report import header_geometry

    cfg = PayloadConfig(storage=Storage(30.0, 20.0, 8.0), lever_arm_body_m=(0.05, 0.0, 0.12), range_sigma_m=0.03)
    path = tmp_path / "x.pslog"
    SampleLogWriter(path, cfg.log_header(), fsync=False).close()
    log = read_samplelog(path)
    storage, frame, lever = header_geometry(log, path)
    assert (storage.length_m, storage.width_m, storage.height_m) == (30.0, 20.0, 8.0)
    assert frame == StorageFrame() and list(lever) == [0.05, 0.0, 0.12]
    err = SensorErrorModel.from_header(log.header)
    assert (err.range_sigma_m, err.range_sigma_rel, err.resolution_m) == (0.03, 0.01, 0.01)
    assert log.header["servo_calibration"]["center_us"] == 1500.0
    json.dumps(log.header)


def test_that_extra_keys_are_appended_but_cannot_replace_a_standard_one():
    h = header(extra={"payload": {"rate_hz": 500.0}})
    assert list(h)[-1] == "payload"
    with pytest.raises(ValueError, match="storage"):
        header(extra={"storage": {}})


@pytest.mark.parametrize("lever", [(0.0, 0.0), (0.0, float("nan"), 0.0), ("a", 0.0, 0.0)])
def test_that_a_bad_lever_arm_is_refused(lever):
    with pytest.raises(ValueError, match="lever arm"):
        header(lever_arm_body_m=lever)


@pytest.mark.parametrize(("kw", "name"), [({"rate_hz": 0.0}, "rate_hz"), ({"range_sigma_m": -1.0}, "range_sigma_m"),
                                          ({"max_range_m": float("inf")}, "max_range_m"), ({"model": ""}, "model")])
def test_that_a_bad_sensor_value_is_refused_by_name(kw, name):
    args = {"rate_hz": 500.0, **kw}
    with pytest.raises(ValueError, match=name):
        sensor_spec(**args)


def test_that_created_utc_defaults_to_now_in_iso_utc():
    h = header(created_utc=None)
    assert h["created_utc"].endswith("+00:00") and len(h["created_utc"]) == 25


def test_that_a_header_round_trips_through_its_typed_form():
    d = header(extra={"servo_calibration": {"center_us": 1490.0, "us_per_rad": 320.0, "min_us": 1000.0,
                                            "max_us": 2000.0, "slew_rad_s": 5.0, "lag_s": 0.02},
                      "servo_drive": {"t0_s": 1.5, "frame_s": 0.02}, "payload": {"i2c": "i2c:1"}})
    typed = LogHeader.from_dict(json.loads(json.dumps(d)))
    assert typed.servo_calibration is not None and typed.servo_calibration.center_us == 1490.0
    assert typed.servo_drive == ServoDrive(1.5, 0.02) and typed.servo.eq1() == named_waveform("sinusoidal", 4.0, 3)
    assert typed.extra == {"payload": {"i2c": "i2c:1"}}
    assert typed.to_dict() == d and list(typed.to_dict()) == list(d)


def test_that_the_payload_programs_header_parses_as_a_typed_header():
    typed = LogHeader.from_dict(PayloadConfig().log_header(sweep_t0_s=0.25))
    assert typed.source == "payload" and typed.sensor.model == LIDARLITE_V3.model
    assert typed.servo_drive is not None and typed.servo_drive.t0_s == 0.25


@pytest.mark.parametrize(("edit", "named"), [
    (lambda h: h.pop("storage"), "storage"),
    (lambda h: h["sensor"].pop("rate_hz"), "rate_hz"),
    (lambda h: h["servo"].update(direction=2), "direction"),
    (lambda h: h["servo"].update(shape_c="x"), "shape_c"),
    (lambda h: h["storage_frame"].update(heading_rad=None), "storage_frame"),
    (lambda h: h.update(lever_arm_body_m=[0, 0]), "lever arm"),
    (lambda h: h.update(mission_id=5), "mission_id"),
    (lambda h: h.update(servo_drive={"t0_s": 0.0, "frame_s": -1.0}), "servo drive"),
    (lambda h: h.update(servo_drive={"t0_s": 0.0, "frame_s": 1e-9}), "servo drive"),  # no pulse fits in it
])
def test_that_a_malformed_header_is_refused_naming_what_is_wrong(edit, named):
    h = json.loads(json.dumps(header()))
    edit(h)
    with pytest.raises(ValueError, match=named):
        LogHeader.from_dict(h)


def test_that_a_servo_calibration_value_given_as_a_json_boolean_is_refused():
    # Built here, not read from tests/golden: the payload-only install runs tests/firmware_py alone.
    h = dict(header())
    h["servo_calibration"] = {**asdict(ServoCalibration()), "lag_s": True}
    with pytest.raises(ValueError, match=r"servo_calibration\.lag_s must be a finite number"):
        LogHeader.from_dict(rewritable_header(h))


def test_that_the_site_record_round_trips_and_a_malformed_one_is_named():
    site = Site.of(-33.9, 151.2, 30.0, 30.0)
    h = PayloadConfig(storage=Storage(), site=site, frame=site.frame_about()).log_header()
    assert h["site"] == {"lat_deg": -33.9, "lon_deg": 151.2, "alt_m": 30.0, "heading_deg": 30.0}
    assert LogHeader.from_dict(h).site == site
    assert LogHeader.from_dict(h).to_dict() == h
    with pytest.raises(ValueError, match=r"site is malformed.*latitude"):
        LogHeader.from_dict({**h, "site": {**h["site"], "lat_deg": 91.0}})


def test_that_a_payload_frame_that_is_not_its_site_about_the_origin_it_sends_is_refused():
    site = Site.of(-33.9, 151.2, 30.0, 30.0)
    PayloadConfig(site=site, frame=site.frame_about(), send_origin=site.corner.as_tuple())  # agrees
    with pytest.raises(ValueError, match="is not the site"):
        PayloadConfig(site=site, frame=StorageFrame(), send_origin=site.corner.as_tuple())  # heading 0, not 30
