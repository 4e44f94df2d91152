"""Firmware in the loop: the unchanged payload code, lockstep, against the batch sample path."""

import math
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest
from pymavlink import mavutil

from firmware_py.core.samplelog import SampleFlags, read_samplelog
from firmware_py.core.servo_model import ServoCalibration
from firmware_py.core.storage import Storage
from firmware_py.hal.mavlink_link import COMPANION_COMPONENT_ID
from ground.pointcloud import cloud_from_samples
from ground.report import ReportOptions, survey_from_samples
from ground.surface import grid_volume
from sitl.faults.injector import FaultSpec
from sitl.missions.rectangle import Mission
from sitl.runners.flight import FlownMission
from sitl.runners.fly import FlyConfig, log_header
from sitl.runners.lockstep_payload import SURVEY_FLOWN, fly_firmware
from sitl.sensing.batch_sampler import sample_flight
from sitl.world import stockpile as piles
from sitl.world.raycast import World

pytestmark = pytest.mark.long  # scheduled first (tests/conftest.py)

BOOT_OFFSET_S = 1234.5


MOUNT = FaultSpec(servo_offset_deg=3.0, servo_scale_pct=5.0, boresight_deg=2.0, sweep_yaw_deg=1.0)
"""A mount that is not what the log says: the firmware's emulated servo and LiDAR, and the batch sampler, each
fly it their own way (the self-calibration tests fly it with either)."""


@pytest.fixture(scope="module")
def small_flight(tmp_path_factory):
    """At 2 m/s in a 20 x 14 x 10 m building: a 34 s survey, still some 17,000 samples to compare. The mount is
    MOUNT's, in both paths."""
    cfg = FlyConfig(mission=Mission(storage=Storage(20, 14, 10), p_traj=0.2, altitude_m=9.0, speed_m_s=2.0),
                    stockpile="1", payload="firmware", faults=MOUNT)
    log = tmp_path_factory.mktemp("fil") / "samples.pslog"
    run = fly_firmware(cfg, log, log_header(cfg, cfg.servo_waveform()), latency_ms=(5, 30),
                       boot_offset_s=BOOT_OFFSET_S, tlog_path=log.with_name("telemetry.tlog"), faults=MOUNT)
    return cfg, run, resampled(cfg, run, log, MOUNT), log


def resampled(cfg: FlyConfig, run, log, mount: FaultSpec):
    """The firmware flight's true trajectory sampled again by the batch path, with the servo model from the sweep's
    start the program logged, through `mount`."""
    flown = FlownMission(run.true_t_s, run.true_states, 0.0, 0.0, True, [])
    world = World(cfg.mission.storage, piles.resolve("1", cfg.mission.storage))
    sweep_t0_s = read_samplelog(log).header["servo_drive"]["t0_s"]  # the program starts its sweep once synced
    return sample_flight(flown.trajectory_at(run.records["t_s"]), cfg.servo_waveform(), world, cfg.lidar,
                         cfg.lever_arm_body_m, cfg.frame, servo=ServoCalibration(), servo_t0_s=sweep_t0_s,
                         servo_gain=mount.servo_gain, servo_offset_rad=mount.servo_offset_rad,
                         boresight=mount.boresight)


def test_that_the_firmware_flight_completes_at_500_hz_with_every_sample_posed(small_flight):
    _, run, _, _ = small_flight
    assert run.completed
    s = run.records
    assert np.median(np.diff(s["t_s"])) == pytest.approx(0.002, abs=1e-6)
    assert len(s) == pytest.approx(run.duration_s * 500, rel=0.02)
    stale = (s["flags"] & (SampleFlags.STALE_POSE | SampleFlags.NO_POSE)) != 0
    assert stale.mean() < 0.001  # with 5-30 ms latency every sample still waits for its pose
    assert run.lidar_counters["timeouts"] == 0 and run.lidar_counters["bus_errors"] == 0


def test_that_firmware_and_batch_points_agree_to_2_cm_median(small_flight):
    cfg, run, batch, log = small_flight
    ok = (run.records["flags"] == 0) & (batch["flags"] == 0)
    assert ok.mean() > 0.7
    # Both ranged through the same wrong mount: the batch sampler square gives ranges a mount's worth apart.
    assert np.median(np.abs(run.records["range_m"][ok] - batch["range_m"][ok])) < 0.02
    square = resampled(cfg, run, log, FaultSpec())
    assert np.median(np.abs(run.records["range_m"][ok] - square["range_m"][ok])) > 0.05
    pf = cloud_from_samples(run.records[ok], cfg.lever_arm_body_m, cfg.frame).points_w
    pb = cloud_from_samples(batch[ok], cfg.lever_arm_body_m, cfg.frame).points_w
    assert np.median(np.linalg.norm(pf - pb, axis=1)) < 0.02


def test_that_firmware_and_batch_volumes_agree_to_0_1_percent(small_flight):
    """With the log's own header (the servo's calibration and the sweep's start, which the self-calibration
    re-simulates the shaft from), each path's mount is found from the building and the volumes agree."""
    cfg, run, batch, log = small_flight
    header = read_samplelog(log).header
    lever = np.array(cfg.lever_arm_body_m)
    vols = []
    for rec in (run.records, batch):
        sv = survey_from_samples(rec, header, cfg.mission.storage, cfg.frame, lever, ReportOptions(plots=False))
        assert all(sv.mount.applied)
        vols.append(grid_volume(sv.heights, sv.grid))
    assert abs(vols[0] - vols[1]) / vols[1] < 0.001


def _companion_messages(tlog: Path) -> list:
    """What the payload program sent, as the autopilot logged it in its .tlog."""
    conn = mavutil.mavlink_connection(str(tlog), dialect="ardupilotmega")
    out = []
    while (msg := conn.recv_match(type=["NAMED_VALUE_FLOAT", "STATUSTEXT", "SET_GPS_GLOBAL_ORIGIN"])) is not None:
        if msg.get_srcComponent() == COMPANION_COMPONENT_ID:
            out.append(msg)
    conn.close()
    return out


def test_that_the_programs_health_messages_reach_the_autopilots_tlog(small_flight):
    _, run, _, log = small_flight
    msgs = _companion_messages(log.with_name("telemetry.tlog"))
    values = [m for m in msgs if m.get_type() == "NAMED_VALUE_FLOAT"]
    texts = [m.text for m in msgs if m.get_type() == "STATUSTEXT"]
    assert {m.name for m in values} >= {"PS_RATE", "PS_LOGGED", "PS_POSEAGE"}
    assert len(values) == run.result.health.values_sent  # every one sent arrived (no loss on this link)
    logged = [m.value for m in values if m.name == "PS_LOGGED"]
    assert logged == sorted(logged) and logged[-1] > 0.9 * len(run.records) - 500
    assert texts[0] == "pilescan: started, 500 Hz" and texts[-1] == f"pilescan: stopping: {SURVEY_FLOWN}"
    assert any(m.get_type() == "SET_GPS_GLOBAL_ORIGIN" for m in msgs)  # the EKF origin went out first


def test_that_the_program_stops_when_the_survey_is_flown_and_writes_its_header(small_flight):
    cfg, run, _, log = small_flight
    assert run.result.stop_reason == SURVEY_FLOWN and run.result.close_errors == ()
    header = read_samplelog(log).header
    expected = log_header(cfg, cfg.servo_waveform())
    for key in ("source", "mission", "mission_id", "storage", "storage_frame", "servo", "lever_arm_body_m"):
        assert header[key] == expected[key], key
    assert header["servo_calibration"] == asdict(ServoCalibration())
    assert header["servo_drive"]["t0_s"] <= run.records["t_s"][0]


def _noisy_flight(tmp_path, noise, seed=3):
    """At 2 m/s in a 20 x 14 x 10 m building, turning at 60 deg/s: a 28 s survey, still some 13,000 samples (some
    1,400 pose messages of 50 Hz) to take the noise's statistics over: what is tested is the noise, not the path."""
    mission = Mission(storage=Storage(20, 14, 10), p_traj=0.2, altitude_m=9.0, speed_m_s=2.0,
                      yaw_rate_max_rad_s=math.radians(60.0))
    cfg = FlyConfig(mission=mission, stockpile="1", sensor_noise=noise, seed=seed)
    log = tmp_path / f"{noise}-{seed}.pslog"
    run = fly_firmware(cfg, log, log_header(cfg, cfg.servo_waveform()), boot_offset_s=BOOT_OFFSET_S, seed=seed)
    truth = FlownMission(run.true_t_s, run.true_states, 0.0, 0.0, True, []).trajectory_at(run.records["t_s"])
    return cfg, run, truth, read_samplelog(log).header


def test_that_appendix_a_pose_noise_reaches_the_log_through_the_autopilots_messages_and_repeats(tmp_path):
    from firmware_py.core.sensor_noise import SensorNoise
    cfg, run, truth, header = _noisy_flight(tmp_path, "appendix-a")
    assert run.completed
    assert header["sensor_noise"] == SensorNoise.of("appendix-a", cfg.lidar).record()
    posed = (run.records["flags"] & int(SampleFlags.NO_POSE | SampleFlags.STALE_POSE)) == 0
    s = run.records[posed]
    truth = FlownMission(run.true_t_s, run.true_states, 0.0, 0.0, True, []).trajectory_at(s["t_s"])
    # One error per 50 Hz message; the payload waits for the pose after each sample and interpolates
    # (firmware_py.pose), which smooths white message noise: sqrt(2/3) = 0.82 sigma on average (the batch
    # path's model, sitl.sensing.noise.pose_errors_at), never more than sigma. Extrapolating the newest two,
    # as the payload once did, gave 1.6-2.6 sigma. Wide bounds around the batch path's figure.
    ratio = math.sqrt(2 / 3)
    d_pos = np.column_stack([s["x_m"], s["y_m"], s["z_m"]]) - truth.pos_ned_m
    assert abs(d_pos.mean()) < 0.02
    assert d_pos.std() == pytest.approx(ratio * 0.113, rel=0.2)
    d_roll = s["roll_rad"] - truth.roll_rad
    assert d_roll.std() == pytest.approx(ratio * math.radians(0.143), rel=0.2)
    again = fly_firmware(cfg, tmp_path / "again.pslog", log_header(cfg, cfg.servo_waveform()),
                         boot_offset_s=BOOT_OFFSET_S, seed=3)
    assert np.array_equal(again.records, run.records)


def test_that_datasheet_noise_adds_range_noise_and_no_returns_but_leaves_the_pose_exact(tmp_path):
    _, run, truth, header = _noisy_flight(tmp_path, "datasheet")
    _, clean, clean_truth, clean_header = _noisy_flight(tmp_path, "none")
    assert run.completed and header["sensor_noise"]["model"] == "datasheet" and "sensor_noise" not in clean_header
    d_pos = np.column_stack([run.records["x_m"], run.records["y_m"], run.records["z_m"]]) - truth.pos_ned_m
    c = clean.records
    d_clean = np.column_stack([c["x_m"], c["y_m"], c["z_m"]]) - clean_truth.pos_ned_m
    assert np.abs(d_pos).max() < 2 * np.abs(d_clean).max() + 0.01  # the payload's own interpolation only
    no_ret = int(SampleFlags.NO_RETURN)
    assert (run.records["flags"] & no_ret != 0).sum() > (clean.records["flags"] & no_ret != 0).sum()
