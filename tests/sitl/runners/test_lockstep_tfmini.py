"""The TFMini in the loop, lockstep: the payload's unchanged TFMini driver reads the emulated part's frames
through an in-memory serial port, and its faults (bad frames, garbage on the line, an unplugged sensor)
end as flagged samples, never as ranges or wrong poses; the log stays complete and the operator hears
about an unplugged sensor once."""

import numpy as np
import pytest
from pymavlink import mavutil

from firmware_py.core.frames import beam_rays_w
from firmware_py.core.samplelog import EXCLUDE_FROM_CLOUD, SampleFlags, read_samplelog
from firmware_py.core.sensor import TFMINI_S, Rangefinder
from firmware_py.core.storage import Storage
from firmware_py.hal.mavlink_link import COMPANION_COMPONENT_ID
from ground.report import ReportOptions, survey_from_samples
from ground.surface import grid_volume, volume_error_pct
from sitl.faults.injector import FaultSpec, wrongly_tagged
from sitl.missions.rectangle import Mission
from sitl.runners.fly import FlyConfig, log_header
from sitl.runners.lockstep_payload import SURVEY_FLOWN, fly_firmware
from sitl.world import stockpile as piles
from sitl.world.raycast import World

# 2 m/s: a 38 s survey instead of 60 s at the default 1 m/s, long enough for every fault window below and the samples
# after them; the ranges still match the world to the 1 cm quantisation (timing errors grow with speed: 90 % of them
# under 1.5 cm here).
CFG = FlyConfig(mission=Mission(storage=Storage(30, 20, 10), p_traj=0.25, altitude_m=9.0, speed_m_s=2.0),
                stockpile="1", payload="firmware", rangefinder=Rangefinder.TFMINI)
SENSOR_ERROR = int(SampleFlags.SENSOR_ERROR)


def fly(tmp_path, survey=True, **faults):
    """The flight with these faults: its run, log, the ground station's volume error (None with survey=False: a test
    of the log and the operator's messages alone) and its folder."""
    log_path = tmp_path / "samples.pslog"
    run = fly_firmware(CFG, log_path, log_header(CFG, CFG.servo_waveform()), tlog_path=tmp_path / "telemetry.tlog",
                       faults=FaultSpec(seed=5, **faults) if faults else None, seed=5)
    log = read_samplelog(log_path)
    if not survey:
        return run, log, None, tmp_path
    sv = survey_from_samples(log.samples, log.header, CFG.mission.storage, CFG.frame,
                             np.array(CFG.lever_arm_body_m), ReportOptions(plots=False))
    ve = volume_error_pct(grid_volume(sv.heights, sv.grid), piles.resolve("1", CFG.mission.storage).volume_m3)
    return run, log, ve, tmp_path


def lidar_texts(tlog):
    """The payload's STATUSTEXTs about its rangefinder, as the autopilot logged them."""
    conn = mavutil.mavlink_connection(str(tlog), dialect="ardupilotmega")
    out = []
    while (msg := conn.recv_match(type="STATUSTEXT")) is not None:
        if msg.get_srcComponent() == COMPANION_COMPONENT_ID and "LiDAR" in msg.text:
            out.append(msg.text)
    conn.close()
    return out


def range_errors(log):
    """Each unflagged sample's range minus the range ray traced from its logged pose and servo angle."""
    s = log.samples
    good = s[(s["flags"] & int(EXCLUDE_FROM_CLOUD)) == 0]
    world = World(CFG.mission.storage, piles.resolve("1", CFG.mission.storage), max_range_m=TFMINI_S.max_range_m)
    o, d = beam_rays_w(np.column_stack([good["x_m"], good["y_m"], good["z_m"]]), good["roll_rad"],
                       good["pitch_rad"], good["yaw_rad"], good["servo_rad"],
                       np.array(log.header["lever_arm_body_m"]), CFG.frame)
    return good["range_m"] - world.cast(o, d).range_m


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    return fly(tmp_path_factory.mktemp("clean"))


def test_that_the_tfmini_flight_logs_one_sample_per_frame_with_its_datasheet_in_the_header(clean):
    run, log, _ve, where = clean
    assert run.completed and run.result.stop_reason == SURVEY_FLOWN
    s = log.samples
    assert np.median(np.diff(s["t_s"])) == pytest.approx(0.01, abs=1e-6)  # the loop follows the 100 Hz frames
    assert len(s) == pytest.approx(run.duration_s * 100, rel=0.03)
    assert log.header["sensor"] == TFMINI_S.to_dict()
    assert log.header["payload"]["rangefinder"] == "tfmini"
    c = run.lidar_counters
    assert c["timeouts"] == c["bus_errors"] == c["bad_checksums"] == c["dropped_backlog"] == 0
    assert not wrongly_tagged(s, run.true_t_s, run.true_states).any()
    assert lidar_texts(where / "telemetry.tlog") == []  # no rangefinder trouble reported on a clean flight


def test_that_tfmini_ranges_match_the_world_from_their_logged_pose_and_servo_angle(clean):
    _run, log, ve, _where = clean
    err = np.abs(range_errors(log))
    err = err[np.isfinite(err)]
    assert np.median(err) < 0.01 and np.percentile(err, 90) < 0.03  # the 1 cm quantisation, and timing
    assert ve < 2.0


def test_that_bad_frames_and_garbage_are_flagged_samples_never_ranges_or_wrong_poses(tmp_path, clean):
    run, log, ve, _where = fly(tmp_path, tfmini_bad_frame_pct=5, tfmini_garbage_pct=5)
    s = log.samples
    bad_sent = run.faults["tfmini_bad_frames_sent"]
    flagged = np.count_nonzero(s["flags"] & SENSOR_ERROR)
    assert bad_sent > 100 and run.faults["tfmini_garbage_bursts"] > 100
    # Each frame lost to its checksum is one flagged sample (garbage makes few more: a stray 0x59 0x59);
    # the part streams from power-on, so a few bad frames went by before the logging started.
    assert bad_sent * 0.95 <= flagged <= bad_sent * 1.1
    assert len(s) == pytest.approx(len(clean[1].samples), rel=0.01)  # one sample per frame: nothing missing
    assert not wrongly_tagged(s, run.true_t_s, run.true_states).any()
    err = np.abs(range_errors(log))
    clean_err = np.abs(range_errors(clean[1]))
    assert np.percentile(err[np.isfinite(err)], 99) <= np.percentile(clean_err[np.isfinite(clean_err)], 99) + 0.01
    assert abs(ve - clean[2]) < 0.5
    assert log.blocks_corrupt == 0 and log.blocks_truncated == 0


def test_that_an_unplugged_sensor_is_flagged_reported_once_and_recovers_when_plugged_back(tmp_path, clean):
    run, log, ve, _where = fly(tmp_path, tfmini_unplug=(15.0, 3.0))
    assert run.completed and run.faults["tfmini_unplugs"] == 1
    s = log.samples
    err = np.flatnonzero(s["flags"] & SENSOR_ERROR)
    # The unplugged seconds, and only they, are flagged: a timed-out read every three frame periods.
    span = s["t_s"][err[-1]] - s["t_s"][err[0]]
    assert 2.9 <= span <= 3.1
    assert np.all(s["flags"][err[0]:err[-1] + 1] & SENSOR_ERROR)  # no range slipped in between
    assert 3.0 / 0.03 * 0.9 <= len(err) <= 3.0 / 0.03 + 3
    assert run.lidar_counters["timeouts"] >= 90
    after = s[err[-1] + 1:]
    assert np.count_nonzero(after["flags"] & SENSOR_ERROR) == 0 and len(after) > 1000  # back, and stays back
    assert not wrongly_tagged(s, run.true_t_s, run.true_states).any()
    assert log.blocks_corrupt == 0 and log.blocks_truncated == 0
    texts = lidar_texts(tmp_path / "telemetry.tlog")
    assert sum("failing" in t for t in texts) == 1 and texts[-1] == "pilescan: LiDAR ok again"
    assert abs(ve - clean[2]) < 1.0


def test_that_a_sensor_unplugged_for_good_leaves_a_complete_flagged_log_and_one_failure(tmp_path):
    run, log, _ve, _where = fly(tmp_path, survey=False, tfmini_unplug=(20.0, float("inf")))
    assert run.completed and run.result.stop_reason == SURVEY_FLOWN  # the payload flies on, logging
    s = log.samples
    err = np.flatnonzero(s["flags"] & SENSOR_ERROR)
    assert np.all(s["flags"][err[0]:] & SENSOR_ERROR) and s["t_s"][-1] - s["t_s"][err[0]] > 10.0
    assert log.blocks_corrupt == 0 and log.blocks_truncated == 0
    texts = lidar_texts(tmp_path / "telemetry.tlog")
    assert sum("failing" in t for t in texts) == 1 and not any("ok again" in t for t in texts)
