"""The payload's configuration (firmware_py/payload_config.py): a bad value refused in one line naming it, the
defaults a Raspberry Pi survey starts from, and the header the ground station reads."""

from __future__ import annotations

import pytest

from firmware_py.payload_config import PayloadConfig


@pytest.mark.parametrize(("field", "value", "words"), [
    ("rate_hz", 0.0, "rate"),
    ("rate_hz", float("nan"), "rate"),
    ("preset", "turbo", "preset"),
    ("waveform", "square", "waveform"),
    ("initial_position", 20, "initial position"),
    ("lever_arm_body_m", (0.0, 0.0), "lever arm"),
    ("lever_arm_body_m", (0.0, float("inf"), 0.0), "lever arm"),
    ("duration_s", 0.0, "duration"),
    ("stream_url", "tcp:1.2.3.4:5", "stream"),
    ("stream_url", "udp:host:70000", "port"),
    ("send_origin", (91.0, 0.0, 0.0), "latitude"),
    ("mavlink_url", "bogus", "MAVLink"),
    ("mavlink_url", "mqtt:host:1883", "MAVLink link scheme 'mqtt'"),  # no backend: refused now, not at take-off
    ("i2c_url", "spi:0", "unknown scheme 'spi'"),
    ("mavlink_url", "udpout:127.0.0.1:0", "port"),
    ("i2c_url", "i2c:abc", "I2C"),
    ("pwm_url", "servo0", "PWM"),
    ("i2c_address", 0x80, "address"),
    ("range_sigma_m", -0.1, "range_sigma_m"),
    ("records_per_block", 0, "block"),
    ("max_pose_wait_s", 0.0, "pose wait"),
])
def test_that_a_bad_config_value_is_refused_in_one_line_naming_it(field, value, words):
    with pytest.raises(ValueError) as err:
        PayloadConfig(**{field: value})
    msg = str(err.value)
    assert words.lower() in msg.lower() and "\n" not in msg


def test_that_the_default_config_is_the_papers_500_hz_survey_on_a_raspberry_pi():
    cfg = PayloadConfig()
    assert cfg.rate_hz == 500.0 and cfg.preset == "fast-500hz"
    assert (cfg.mavlink_url, cfg.i2c_url, cfg.pwm_url) == ("udpout:127.0.0.1:14550", "i2c:1", "pwm:sysfs:0:0")
    assert cfg.fsync and not cfg.force and cfg.duration_s is None and cfg.stream_url is None


def test_that_the_log_header_has_what_the_ground_station_reads():
    from ground.pointcloud import SensorErrorModel
    header = PayloadConfig(range_sigma_m=0.03, lever_arm_body_m=(0.1, 0.0, 0.2)).log_header()
    err = SensorErrorModel.from_header(header)
    assert (err.range_sigma_m, err.range_sigma_rel, err.resolution_m) == (0.03, 0.01, 0.01)
    assert header["source"] == "payload" and header["lever_arm_body_m"] == [0.1, 0.0, 0.2]
    assert header["storage"] == {"length_m": 60.0, "width_m": 40.0, "height_m": 15.0}
    assert header["payload"]["lidar_preset"] == "fast-500hz"
