"""Payload health messages: within MAVLink's limits, encodable, and sent on the right state changes."""

from __future__ import annotations

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.health import (
    NAME_MAX,
    TEXT_CHUNKS_MAX,
    TEXT_MAX,
    VALUE_NAMES,
    HealthMonitor,
    HealthSnapshot,
    PoseState,
    SensorState,
    named_value_msg,
    statustext_msgs,
)

S = 1_000_000_000
T0 = 5_000 * S


def roundtrip(msg):
    """Pack with a MAVLink 2 encoder and decode the bytes again, as the GCS would."""
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=191)
    return mavlink.MAVLink(None).decode(bytearray(msg.pack(mav)))


def snap(t_s: float, readings: int = 0, errors: int = 0, pose_ok: bool = True, age: float | None = 0.01,
         **kw) -> HealthSnapshot:
    return HealthSnapshot(t_ns=T0 + round(t_s * S), readings=readings, logged=readings, sensor_errors=errors,
                          pose_ok=pose_ok, pose_age_s=age, **kw)


def texts(msgs) -> list[tuple[int, str]]:
    return [(m.severity, m.text) for m in msgs if m.get_type() == "STATUSTEXT"]


def values(msgs) -> dict[str, float]:
    return {m.name: m.value for m in msgs if m.get_type() == "NAMED_VALUE_FLOAT"}


def test_that_value_names_fit_mavlinks_ten_characters_and_survive_encoding():
    for name in VALUE_NAMES:
        assert 0 < len(name) <= NAME_MAX and name.isascii()
        back = roundtrip(named_value_msg(name, 12.5, 1234))
        assert (back.get_type(), back.name, back.value, back.time_boot_ms) == ("NAMED_VALUE_FLOAT", name, 12.5, 1234)


@pytest.mark.parametrize("name", ["", "PS_TOO_LONG_", "PS_RÄTE", None])
def test_that_a_name_mavlink_would_truncate_is_refused(name):
    with pytest.raises(ValueError, match="NAMED_VALUE_FLOAT name"):
        named_value_msg(name, 1.0, 0)


def test_that_a_statustext_that_fits_is_one_message_and_encodes():
    [msg] = statustext_msgs(mavlink.MAV_SEVERITY_WARNING, "x" * TEXT_MAX)
    back = roundtrip(msg)
    assert (back.get_type(), back.text, back.id, back.severity) == ("STATUSTEXT", "x" * TEXT_MAX, 0,
                                                                    mavlink.MAV_SEVERITY_WARNING)
    assert [roundtrip(m).text for m in statustext_msgs(mavlink.MAV_SEVERITY_INFO, "pose ok é")] == ["pose ok ?"]
    with pytest.raises(ValueError):
        statustext_msgs(9, "bad severity")


@pytest.mark.parametrize("length", [51, 99, 100, 150, 199])
def test_that_a_long_statustext_goes_in_mavlink2_chunks_that_join_to_the_whole_text(length):
    """A stop's reason is often longer than STATUSTEXT's 50 characters: cut there, it ended mid-word; in chunks
    sharing an id (QGroundControl joins them), the last shorter than 50, its NUL ending the text."""
    text = ("stopping: error: cannot open MAVLink link udpout:127.0.0.1:14999 " * 4)[:length]
    backs = [roundtrip(m) for m in statustext_msgs(mavlink.MAV_SEVERITY_CRITICAL, text)]
    assert len({b.id for b in backs}) == 1 and backs[0].id != 0
    assert [b.chunk_seq for b in backs] == list(range(len(backs))) and len(backs) <= TEXT_CHUNKS_MAX
    assert all(len(b.text) == TEXT_MAX for b in backs[:-1]) and len(backs[-1].text) < TEXT_MAX
    assert "".join(b.text for b in backs) == text
    again = statustext_msgs(mavlink.MAV_SEVERITY_CRITICAL, text)
    assert again[0].id != backs[0].id  # another text, another id


def test_that_a_text_longer_than_the_chunks_hold_is_cut_after_a_whole_word():
    text = "preflight FAIL: " + ", ".join(["autopilot", "pose", "EKF sources", "rangefinder", "servo sweep"] * 5)
    joined = "".join(roundtrip(m).text for m in statustext_msgs(mavlink.MAV_SEVERITY_CRITICAL, text))
    assert len(joined) < TEXT_MAX * TEXT_CHUNKS_MAX and joined.endswith("~")
    assert text.startswith(joined[:-1]) and text[len(joined) - 1] == " "  # the cut is between two words


def test_that_every_message_the_monitor_sends_encodes_and_fits():
    mon = HealthMonitor(T0)
    msgs = mon.event(mavlink.MAV_SEVERITY_INFO, "started, 500 Hz with a very long tail of words here")
    msgs += mon.update(snap(0.0, pose_ok=False, age=None))
    msgs += mon.update(snap(1.0, readings=500, errors=3))
    msgs += mon.update(snap(2.0, readings=1000, errors=503, pose_ok=False, age=0.4))
    msgs += mon.update(snap(11.0, readings=1500, errors=503))
    assert msgs
    for m in msgs:
        back = roundtrip(m)
        assert back.get_type() in ("STATUSTEXT", "NAMED_VALUE_FLOAT")
        if back.get_type() == "STATUSTEXT":
            assert len(back.text) <= TEXT_MAX and (back.chunk_seq > 0 or back.text.startswith("pilescan: "))
        else:
            assert len(back.name) <= NAME_MAX


def test_that_values_go_once_per_period_with_the_sample_rate():
    mon = HealthMonitor(T0, period_s=1.0)
    first = values(mon.update(snap(0.0, pose_ok=False, age=None)))
    assert set(first) == set(VALUE_NAMES) and first["PS_POSEAGE"] == -1.0  # no pose yet
    assert mon.update(snap(0.5, readings=250)) == []  # not due
    second = values(mon.update(snap(1.0, readings=500, errors=2, stale=7, overruns=1)))
    assert second["PS_RATE"] == pytest.approx(500.0)
    assert (second["PS_I2CERR"], second["PS_STALE"], second["PS_OVERRUN"], second["PS_LOGGED"]) == (2, 7, 1, 500)
    assert second["PS_POSEAGE"] == pytest.approx(0.01)
    assert mon.status().values_sent == 2 * len(VALUE_NAMES)


def test_that_pose_acquired_lost_and_regained_are_each_said_once():
    mon = HealthMonitor(T0)
    assert texts(mon.update(snap(0, pose_ok=False, age=None))) == []
    assert texts(mon.update(snap(1))) == [(mavlink.MAV_SEVERITY_INFO, "pilescan: pose acquired")]
    assert texts(mon.update(snap(2))) == []
    lost = texts(mon.update(snap(3, pose_ok=False, age=0.53)))
    assert lost == [(mavlink.MAV_SEVERITY_WARNING, "pilescan: pose lost (age 0.53 s)")]
    assert texts(mon.update(snap(4, pose_ok=False, age=1.5))) == []
    assert texts(mon.update(snap(5))) == [(mavlink.MAV_SEVERITY_NOTICE, "pilescan: pose regained")]


@pytest.mark.parametrize(("converged", "status", "why", "heard"), [
    (False, "no HEARTBEAT from the autopilot (system 1) ...", "no HEARTBEAT from autopilot", False),  # the cause first
    (False, "waiting for TIMESYNC replies", "time sync not converged", True),
    (True, "no LOCAL_POSITION_NED from the autopilot yet: ...", "no local position (EKF origin?)", True),
    (True, "no ATTITUDE from the autopilot yet", "no ATTITUDE stream", True),
])
def test_that_a_pose_missing_ten_seconds_after_start_is_reported_once_with_why(converged, status, why, heard):
    mon = HealthMonitor(T0)
    kw = {"pose_ok": False, "age": None, "timesync_converged": converged, "pose_status": status,
          "autopilot_heard": heard}
    for t in range(10):
        assert texts(mon.update(snap(t, **kw))) == []
    assert texts(mon.update(snap(10, **kw))) == [(mavlink.MAV_SEVERITY_WARNING, f"pilescan: no pose: {why}")]
    assert texts(mon.update(snap(11, **kw))) == []


def test_that_lidar_errors_failure_and_recovery_are_reported_on_change():
    mon = HealthMonitor(T0)
    mon.update(snap(0))
    assert texts(mon.update(snap(1, readings=500))) == []
    assert texts(mon.update(snap(2, readings=1000, errors=4))) == [
        (mavlink.MAV_SEVERITY_WARNING, "pilescan: LiDAR errors: 4 of 500 reads")]
    assert texts(mon.update(snap(3, readings=1500, errors=9))) == []  # still erring: said already
    assert texts(mon.update(snap(4, readings=2000, errors=509))) == [
        (mavlink.MAV_SEVERITY_ERROR, "pilescan: LiDAR failing: 500 errors/500 reads")]
    assert texts(mon.update(snap(5, readings=2500, errors=509))) == [
        (mavlink.MAV_SEVERITY_NOTICE, "pilescan: LiDAR ok again")]
    assert texts(mon.update(snap(6, readings=2500, errors=509))) == []  # no readings: nothing to judge


def test_that_a_clock_going_back_does_not_silence_the_monitor():
    mon = HealthMonitor(T0)
    mon.update(snap(10))
    assert values(mon.update(snap(1)))  # time went back: send at once rather than in 9 s


def test_that_a_bad_period_is_refused():
    for bad in (0.0, -1.0, float("nan"), 1e6):
        with pytest.raises(ValueError, match="health period"):
            HealthMonitor(T0, period_s=bad)


def test_that_the_status_follows_pose_and_sensor_states_as_enums_in_a_frozen_snapshot():
    mon = HealthMonitor(T0)
    mon.update(snap(0, pose_ok=False, age=None))
    start = mon.status()
    assert (start.pose_state, start.sensor_state) == (PoseState.WAITING, SensorState.OK)
    mon.update(snap(1, readings=500))
    mon.update(snap(2, readings=1000, errors=500))
    now = mon.status()
    assert (now.pose_state, now.sensor_state) == (PoseState.OK, SensorState.FAILED)
    assert start.pose_state is PoseState.WAITING  # the earlier snapshot did not change
    assert now.as_dict()["sensor_state"] == "failed" and now.texts_sent == 2  # pose acquired, LiDAR failing
    with pytest.raises(AttributeError):
        now.rate_hz = 0.0


def test_that_sensor_error_samples_are_sent_and_a_part_stuck_resetting_is_not_called_ok():
    """Readings during an automatic reset are logged SENSOR_ERROR but are no failed transfer: the
    health values carry both counts, and the LiDAR state follows the larger."""
    mon = HealthMonitor(T0)
    mon.update(snap(0.0))
    msgs = mon.update(snap(1.0, readings=500, errors=0, sensor_error_samples=500))
    assert values(msgs)["PS_SENSERR"] == 500 and values(msgs)["PS_I2CERR"] == 0
    assert texts(msgs) == [(mavlink.MAV_SEVERITY_ERROR, "pilescan: LiDAR failing: 500 errors/500 reads")]
