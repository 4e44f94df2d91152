"""tools.pose_correction_campaign: what it flies and how it tabulates (the flights themselves run in the campaign)."""

import math
from pathlib import Path

import numpy as np
import pytest
import trimesh

from tools.pose_correction_campaign import (
    Building,
    clock_offset_s,
    kept_flight_crash,
    on_log_clock,
    own_pile,
    table,
    trajectory_rms_m,
)


def test_that_the_paper_building_adds_no_fly_arguments_and_an_own_building_adds_its_size_and_altitude():
    assert Building().fly_args() == []
    assert Building("40x25x10", 7.0).fly_args() == ["--storage", "40x25x10", "--altitude", "7"]
    assert "40 x 25 x 10 m" in Building("40x25x10", 7.0).describe()


def test_that_an_own_pile_is_written_as_a_mesh_under_the_flight(tmp_path: Path):
    label, path = own_pile("cone:1", Building("40x25x10", 7.0), tmp_path)
    assert label == "cone:1"
    mesh = trimesh.load(path)
    assert mesh.bounds[1][2] <= 7.0 - 2.0 + 1e-6  # its top 2 m under the flight
    assert mesh.bounds[1][0] <= 40.0 and mesh.bounds[1][1] <= 25.0


def test_that_the_table_has_a_row_per_pile_and_profile_and_counts_seeds_against_their_own_error_free_flight():
    rows = [{"profile": prof, "pile": "ridge:2", "p_traj": 5, "seed": seed, "ve_off": off, "ve_on": on,
             "applied": prof != "none", "traj_before_m": 0.5, "traj_after_m": after}
            for prof, seed, off, on, after in [("none", 0, 0.1, 0.1, 0.0), ("none", 1, 0.5, 0.5, 0.0),
                                               ("vio", 0, 3.0, 0.3, 0.05), ("vio", 1, 3.0, 0.6, 0.2)]]
    text = table(rows)
    vio = next(line for line in text.splitlines() if "| vio |" in line)
    assert vio.startswith("| ridge:2 | 5 % | vio | 2 |")
    assert vio.endswith("| 2/2 | 1/2 |  | 0/2 |")  # 0.3 vs 0.1 and 0.6 vs 0.5: both within 0.3 pp; one RMS <= 10 cm


def test_that_the_table_counts_the_corrected_reports_whose_interval_holds_the_truth():
    # the volume's 90 % interval has no term for the pose's own error: the table shows how often it still holds
    rows = [{"profile": prof, "pile": "1", "p_traj": 20, "seed": seed, "ve_off": 1.0, "ve_on": 0.5, "applied": True,
             "traj_before_m": 0.5, "traj_after_m": 0.05, "in_interval": inside}
            for prof, seed, inside in [("none", 0, True), ("vio", 0, True), ("vio", 1, False), ("vio", 2, None)]]
    vio = next(line for line in table(rows).splitlines() if "| vio |" in line)
    assert vio.endswith("| 1/2 | 0/3 |")  # a row from before the column (None) is not counted either way


def test_that_a_flight_that_hit_a_wall_is_counted_as_a_crash_and_left_out_of_the_means_and_targets():
    rows = [{"profile": prof, "pile": "1", "p_traj": 5, "seed": seed, "ve_off": off, "ve_on": on,
             "applied": prof != "none", "traj_before_m": 0.5, "traj_after_m": after}
            for prof, seed, off, on, after in [("none", 0, 0.0, 0.0, 0.0), ("none", 1, 0.0, 0.0, 0.0),
                                               ("flow", 0, 6.0, 0.2, 0.05)]]
    rows.append({"profile": "flow", "pile": "1", "p_traj": 5, "seed": 1, "hit": "the vehicle hit the wall y = W"})
    flow = next(line for line in table(rows).splitlines() if "| flow |" in line)
    assert flow.startswith("| 1 | 5 % | flow | 1 | 0.00 | 6.00 | 0.20 |")  # the crash's numbers are not there
    assert flow.endswith("| 1/1 | 1/1 |  | 1/2 |")
    rows[2] = {**rows[2], "hit": "the vehicle hit the roof"}
    flow = next(line for line in table(rows).splitlines() if "| flow |" in line)
    assert flow.startswith("| 1 | 5 % | flow | 0 |") and flow.endswith("| 2/2 |")


def test_that_a_kept_flight_whose_true_path_left_the_building_is_found_from_its_truth():
    t = np.arange(0.0, 10.0, 0.1)
    path = np.column_stack([30 + 0 * t, 2.0 - 0.25 * t, 12 + 0 * t])  # drifts through the wall y = 0 at 8 s
    truth = {"storage": {"length_m": 60.0, "width_m": 40.0, "height_m": 15.0},
             "pose_error": {"trajectory": {"t_s": t.tolist(), "true_w_m": path.tolist()}}}
    crash = kept_flight_crash(truth)
    assert crash is not None and "the wall y = 0" in crash and "outside the building" in crash
    path[:, 1] = 2.0  # two metres off the wall all the way: clear
    truth["pose_error"]["trajectory"]["true_w_m"] = path.tolist()
    assert kept_flight_crash(truth) is None
    assert kept_flight_crash({**truth, "pose_error": None}) is None  # flown on the truth: the plan keeps clear


def _served(offset_s: float) -> tuple[dict, np.ndarray, np.ndarray]:
    """A truth.json on the simulator's clock (10 Hz, a loop with a drifting estimate) and a payload log of the
    same estimate on a clock offset_s behind, sampled at 500 Hz with centimetre noise."""
    t = np.arange(0.0, 120.0, 0.1)
    true_w = np.column_stack([10 + 8 * np.cos(t / 10), 10 + 5 * np.sin(t / 7), 12 + 0.1 * np.sin(t)])
    est_w = true_w + np.column_stack([0.003 * t, -0.002 * t, 0.05 * np.sin(t / 20)])
    truth = {"pose_error": {"trajectory": {"t_s": t.tolist(), "true_w_m": true_w.tolist(),
                                           "estimated_w_m": est_w.tolist(), "clock": "simulator"}}}
    log_t = np.arange(5.0, 110.0, 0.002) - offset_s
    logged = np.column_stack([np.interp(log_t + offset_s, t, est_w[:, c]) for c in range(3)])
    logged += np.random.default_rng(0).normal(0.0, 0.01, logged.shape)
    return truth, log_t, logged


def test_that_a_served_trajectory_is_put_on_the_payload_logs_clock_by_the_estimate_both_carry():
    truth, log_t, logged = _served(offset_s=37.25)
    offset, apart_m = clock_offset_s(truth["pose_error"]["trajectory"], log_t, logged)
    assert offset == pytest.approx(37.25, abs=0.01)
    assert apart_m < 0.02
    moved = on_log_clock(truth, offset)
    before, _ = trajectory_rms_m(moved, None)
    t = np.asarray(truth["pose_error"]["trajectory"]["t_s"])
    expected = np.sqrt(np.mean(np.sum(np.column_stack([0.003 * t, -0.002 * t, 0.05 * np.sin(t / 20)]) ** 2, axis=1)))
    assert before == pytest.approx(expected, rel=1e-6)


def test_that_a_log_the_trajectory_cannot_cover_is_refused_not_aligned():
    truth, _, _ = _served(offset_s=0.0)  # 120 s of trajectory
    log_t = np.arange(0.0, 400.0, 0.01)  # a log over three times as long: no offset puts half of it inside
    with pytest.raises(ValueError, match="do not overlap"):
        clock_offset_s(truth["pose_error"]["trajectory"], log_t, np.zeros((len(log_t), 3)))


def test_that_a_trajectory_on_the_simulators_clock_is_not_compared_with_a_log_unaligned():
    truth, _, _ = _served(offset_s=0.0)
    with pytest.raises(ValueError, match="align it first"):
        trajectory_rms_m(truth, None)


def test_that_rows_already_computed_are_said_to_be_taken_as_they_are_when_flights_are_to_be_reported_again(
        tmp_path: Path, capsys):
    """--reuse with a --rows file holding every row asked for reports nothing again: the program says so (and
    how to report again) instead of regenerating a table that silently did not change."""
    import json

    from tools.pose_correction_campaign import main
    rows = tmp_path / "rows.jsonl"
    rows.write_text("".join(json.dumps({"profile": prof, "pile": "1", "p_traj": 5, "seed": 0, "ve_off": 0.1,
                                        "ve_on": 0.1, "applied": False, "traj_before_m": 0.0, "traj_after_m": 0.0})
                            + "\n" for prof in ("none", "vio", "flow")))
    assert main(["--seeds", "0", "--piles", "1", "--p-traj", "5", "--keep", str(tmp_path / "runs"), "--reuse",
                 "--rows", str(rows)]) == 0
    err = capsys.readouterr().err
    assert "3 row(s) read from" in err and "not reported again" in err and "leave out --rows" in err
    assert not any((tmp_path / "runs").iterdir())  # nothing flown, nothing reported


def test_that_a_noisy_campaign_flies_with_the_sensor_noise_into_folders_of_its_own(tmp_path: Path, monkeypatch):
    import subprocess

    from firmware_py.core.sensor_noise import SensorNoiseModel
    from tools.pose_correction_campaign import one
    flown = []

    def crash(cmd, **kwargs):  # every flight "hits a wall": no report is made, and the command is what is asked
        flown.append(cmd)
        return subprocess.CompletedProcess(cmd, 4, "", "fly: the vehicle hit the wall x = 0 at 12.0 s\n")
    monkeypatch.setattr(subprocess, "run", crash)
    row = one("vio", "1", 20, 3, tmp_path, sensor_noise=SensorNoiseModel.APPENDIX_A)
    assert row["hit"].startswith("fly: the vehicle hit")
    cmd = flown[-1]
    assert cmd[cmd.index("--sensor-noise") + 1] == "appendix-a"
    assert cmd[cmd.index("--out") + 1] == str(tmp_path / "vio-1-20-3-appendix-a")
    one("vio", "1", 20, 3, tmp_path)  # no noise: the folder and the command are the noise-free campaign's
    assert "--sensor-noise" not in flown[-1] and flown[-1][flown[-1].index("--out") + 1] == str(tmp_path / "vio-1-20-3")


def test_that_the_page_names_the_command_without_this_machine_s_row_files():
    # A campaign split over processes is tabulated by a last call reading their --rows files; the page must name
    # a command a reader can run, which those files are not part of.
    from tools.pose_correction_campaign import regeneration_args
    argv = ["--seeds", "0", "1", "--keep", "runs/pose", "--rows", "/tmp/a.jsonl", "/tmp/b.jsonl", "--reuse",
            "--write", "docs/pose_error.md"]
    assert regeneration_args(argv) == "--seeds 0 1 --keep runs/pose --reuse --write docs/pose_error.md"
    assert regeneration_args(["--rows", "r.jsonl"]) == ""
    assert regeneration_args(["--keep", "k"]) == "--keep k"


def test_that_the_table_compares_signed_volumes_where_the_rows_have_them():
    # -0.94 % against +1.05 %: unsigned Ve puts them 0.11 pp apart, the volumes are 1.99 pp apart
    rows = [{"profile": prof, "pile": "2", "p_traj": 20, "seed": 0, "ve_off": off, "ve_on": on, "dv_off_pct": doff,
             "dv_on_pct": don, "applied": prof != "none", "traj_before_m": 0.5, "traj_after_m": 0.05}
            for prof, off, on, doff, don in [("none", 1.05, 1.05, 1.05, 1.05), ("vio", 2.0, 0.94, 2.0, -0.94),
                                             ("flow", 20.0, 1.0, -20.0, 1.0)]]
    lines = table(rows).splitlines()
    assert next(line for line in lines if "| vio |" in line).endswith("| 0/1 | 1/1 |  | 0/1 |")
    assert next(line for line in lines if "| flow |" in line).endswith("| 1/1 | 1/1 |  | 0/1 |")
    for r in rows:  # rows from before the signed fields: unsigned, as they were
        del r["dv_off_pct"], r["dv_on_pct"]
    assert next(line for line in table(rows).splitlines() if "| vio |" in line).endswith("| 1/1 | 1/1 |  | 0/1 |")


def test_that_the_signed_error_is_the_volume_less_the_truth():
    from tools.pose_correction_campaign import signed_error_pct
    assert signed_error_pct({"volume_m3": 95.0, "true_volume_m3": 100.0}) == pytest.approx(-5.0)
    assert math.isnan(signed_error_pct({"volume_m3": 3.0, "true_volume_m3": 0.0}))


def test_that_the_trajectory_after_the_report_is_placed_with_the_rangefinder_lift_and_the_pose_correction():
    """A flight whose logged height followed the pile is raised by the report before the pose is corrected: the
    trajectory the report stands for is the estimate, raised, then corrected; a lift left out would count a
    rangefinder error the report took out as still there."""
    t = np.arange(0.0, 60.0, 0.1)
    true_w = np.column_stack([t, np.full(len(t), 5.0), np.full(len(t), 12.0)])
    lift = np.where((t > 20) & (t < 40), 0.6, 0.0)  # the pile below for 20 s, its share taken out
    est_w = true_w + np.column_stack([np.full(len(t), 0.2), np.zeros(len(t)), -lift])
    truth = {"pose_error": {"trajectory": {"t_s": t.tolist(), "true_w_m": true_w.tolist(),
                                           "estimated_w_m": est_w.tolist()}}}
    correction = {"applied": True, "knot_t_s": [0.0, 60.0], "knot_values": [[-0.2, 0, 0, 0], [-0.2, 0, 0, 0]]}
    rangefinder = {"applied": True, "lift_t_s": t.tolist(), "lift_at_t_m": lift.tolist()}
    before, after = trajectory_rms_m(truth, correction, rangefinder)
    assert before > 0.3 and after == pytest.approx(0.0, abs=1e-9)
    _, pose_only = trajectory_rms_m(truth, correction)
    assert pose_only == pytest.approx(np.sqrt(np.mean(lift ** 2)))
    _, not_applied = trajectory_rms_m(truth, correction, {**rangefinder, "applied": False})
    assert not_applied == pytest.approx(pose_only)


def test_that_the_trajectory_after_the_report_counts_the_heights_the_sweeps_refined():
    """The report adds the sweeps' floor offsets to the knots' height (`ground.sweep_heights`): left out, the
    trajectory would be judged without a correction the volume was placed with."""
    t = np.arange(0.0, 30.0, 0.1)
    true_w = np.column_stack([t, np.full(len(t), 5.0), np.full(len(t), 12.0)])
    wave = 0.03 * np.sin(2.0 * np.pi * t / 6.0)
    est_w = true_w + np.column_stack([np.zeros(len(t)), np.zeros(len(t)), wave])
    truth = {"pose_error": {"trajectory": {"t_s": t.tolist(), "true_w_m": true_w.tolist(),
                                           "estimated_w_m": est_w.tolist()}}}
    knots = {"applied": True, "knot_t_s": [0.0, 30.0], "knot_values": [[0, 0, 0, 0], [0, 0, 0, 0]]}
    _, knots_only = trajectory_rms_m(truth, knots)
    _, refined = trajectory_rms_m(truth, {**knots, "sweep_heights": {"t_s": t.tolist(), "dz_m": (-wave).tolist()}})
    assert knots_only == pytest.approx(np.sqrt(np.mean(wave ** 2))) and refined == pytest.approx(0.0, abs=1e-9)


def test_that_a_flight_fly_refused_before_take_off_is_no_survey_and_is_counted_as_refused_not_as_a_crash():
    rows = [{"profile": "none", "pile": "2", "p_traj": 25, "seed": 0, "ve_off": 0.1, "ve_on": 0.1, "applied": False,
             "traj_before_m": 0.0, "traj_after_m": 0.0}]
    why = "pilescan-sitl: error: altitude 9 m is too high for --pose-error flow: over the 7.50 m pile ..."
    rows += [{"profile": "flow", "pile": "2", "p_traj": 25, "seed": s, "refused": why} for s in (0, 1)]
    flow = next(line for line in table(rows).splitlines() if "| flow |" in line)
    assert flow.startswith("| 2 | 25 % | flow | 0 | 0.10 |") and flow.endswith("| 0/0 (2 refused by `fly`) |"), flow


def test_that_a_kept_flight_s_uncorrected_report_is_reused_only_when_made_by_the_code_now(tmp_path: Path, monkeypatch):
    """--reuse reports a kept flight with the correction again and keeps its uncorrected report, but only one made by
    the ground station's code as it is now (`tools.source_digest`): one made by older code is made again, so the
    table's uncorrected column is the code's too."""
    import json
    import subprocess

    from firmware_py.core.storage import Storage
    from tools import pose_correction_campaign as campaign
    from tools import source_digest
    work = tmp_path / "runs"
    run = work / "vio-1-5-0"
    run.mkdir(parents=True)
    (run / "truth.json").write_text(json.dumps({"storage": Storage(30, 20, 10).to_dict()}))
    made = []

    def report(cmd, **_kw):
        out = Path(cmd[cmd.index("--out") + 1])
        out.mkdir(parents=True, exist_ok=True)
        (out / "report.json").write_text(json.dumps({"volume_m3": 101.0 + len(made), "true_volume_m3": 100.0,
                                                     "volume_error_pct": 1.0}))
        made.append(out.name)
        return subprocess.CompletedProcess(cmd, 0, "", "")

    monkeypatch.setattr(campaign.subprocess, "run", report)
    first = campaign.one("vio", "1", 5, 0, work, reuse=True)
    assert made == ["vio-1-5-0--no-pose-correction", "vio-1-5-0--pose-correction"]
    again = campaign.one("vio", "1", 5, 0, work, reuse=True)
    assert made[2:] == ["vio-1-5-0--pose-correction"] and again["dv_off_pct"] == first["dv_off_pct"]
    (work / "vio-1-5-0--no-pose-correction" / source_digest.MADE_BY).write_text("older code\n")
    campaign.one("vio", "1", 5, 0, work, reuse=True)
    assert made[3:] == ["vio-1-5-0--no-pose-correction", "vio-1-5-0--pose-correction"]


def test_that_the_trajectory_is_judged_over_the_span_the_correction_was_fitted_on():
    """A networked payload logs the climb and the landing, where no sample is usable and the correction is only held
    at its end's value: the descent after the last knot is not the survey's trajectory (before and after alike)."""
    t = np.arange(0.0, 40.0, 0.1)
    true_w = np.column_stack([t, np.full(len(t), 5.0), np.where(t > 30, 12.0 - (t - 30), 12.0)])
    est_w = true_w + np.column_stack([np.full(len(t), 0.3), np.zeros(len(t)), np.where(t > 30, -1.0, 0.0)])
    truth = {"pose_error": {"trajectory": {"t_s": t.tolist(), "true_w_m": true_w.tolist(),
                                           "estimated_w_m": est_w.tolist()}}}
    correction = {"applied": True, "knot_t_s": [0.0, 15.0, 30.0], "knot_values": [[-0.3, 0, 0, 0]] * 3}
    before, after = trajectory_rms_m(truth, correction)
    assert before == pytest.approx(0.3) and after == pytest.approx(0.0, abs=1e-9)
    whole, _ = trajectory_rms_m(truth, None)  # no correction: the whole trajectory, the descent's metre in it
    assert whole > 0.5
