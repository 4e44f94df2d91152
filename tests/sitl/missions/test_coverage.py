"""The coverage model and planner: what a sweep reaches on the floor, and the least-energy loop reaching a target."""

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.core.frames import StorageFrame
from firmware_py.core.geodesy import global_to_ned
from firmware_py.core.sensor import LIDARLITE_V3
from firmware_py.core.storage import Storage
from firmware_py.core.waveform import named_waveform
from sitl.cli import main
from sitl.missions.coverage import (
    CoverageTarget,
    LoopMission,
    LoopPlan,
    floor_hits_w,
    mission_energy_j,
    plan_coverage,
    predict_coverage,
    worst_coverage,
)
from sitl.missions.qgc_wpl import DEFAULT_ORIGIN, read_qgc_wpl, write_qgc_wpl
from sitl.missions.range_check import RangeLimit
from sitl.missions.rectangle import Mission

WF = named_waveform("semi-triangular", 5.0, 0)
LIDAR = RangeLimit(LIDARLITE_V3.max_range_m)
SMALL = Storage(30.0, 20.0, 10.0)


def test_that_a_leg_sees_a_swath_as_wide_as_the_floor_reach_either_side():
    limit = RangeLimit(15.0)  # from 11.9 m the floor is reached 9.1 m either side of the track
    m = LoopPlan((10.0, 10.0, 10.0, 10.0)).mission(Storage(), 12.0, math.radians(30))
    hits = floor_hits_w(m, WF, limit, LIDARLITE_V3.rate_hz)
    mid_south = hits[(hits[:, 0] > 25) & (hits[:, 0] < 35) & (hits[:, 1] < 20)]
    reach = limit.floor_reach_m(11.9)
    assert reach == pytest.approx(9.13, abs=0.01)
    assert mid_south[:, 1].min() == pytest.approx(10.0 - reach, abs=0.3)
    assert np.abs(mid_south[:, 1] - 10.0).max() <= reach + 1e-6


def test_that_the_rectangle_near_the_walls_is_predicted_to_cover_the_whole_floor():
    near = predict_coverage(Mission(p_traj=0.05), WF, LIDAR, LIDARLITE_V3.rate_hz)
    far = predict_coverage(Mission(p_traj=0.30), WF, LIDAR, LIDARLITE_V3.rate_hz)
    assert near.predicted_ra_pct > 99.5
    assert far.predicted_ra_pct < near.predicted_ra_pct - 5  # the corners are left between a few fan lines


def test_that_floor_out_of_reach_is_not_covered():
    limit = RangeLimit(15.0)
    short = predict_coverage(Mission(p_traj=0.2), WF, limit, LIDARLITE_V3.rate_hz)
    gap_m = 40.0 - 2 * (8.0 + limit.floor_reach_m(11.9))  # the middle strip beyond the reach of both long legs
    assert gap_m > 5
    assert short.predicted_ra_pct <= 100 * (1 - gap_m / 40.0) + 0.1


def test_that_the_planner_reaches_its_target_on_the_model_for_less_energy_than_the_near_rectangle():
    target = CoverageTarget(97.0, WF, LIDAR, LIDARLITE_V3.rate_hz, speeds_m_s=(1.0, 2.0))
    planned = plan_coverage(SMALL, target, altitude_m=6.0)
    again = predict_coverage(planned.mission, WF, LIDAR, LIDARLITE_V3.rate_hz)
    assert again.predicted_ra_pct >= 97.0
    rect = Mission(SMALL, p_traj=0.05, altitude_m=6.0)
    assert planned.energy_j < mission_energy_j(rect)
    assert planned.mission.plan["predicted_ra_pct"] == pytest.approx(again.predicted_ra_pct, abs=1e-3)


def test_that_a_plan_for_several_servo_start_positions_reaches_the_target_at_each():
    others = tuple(named_waveform("semi-triangular", 5.0, k) for k in (4, 13))
    target = CoverageTarget(97.0, WF, LIDAR, LIDARLITE_V3.rate_hz, speeds_m_s=(2.0,), also_waveforms=others)
    planned = plan_coverage(SMALL, target, altitude_m=6.0)
    each = [predict_coverage(planned.mission, wf, LIDAR, LIDARLITE_V3.rate_hz).predicted_ra_pct
            for wf in (WF, *others)]
    assert min(each) >= 97.0
    assert planned.coverage.predicted_ra_pct == pytest.approx(min(each))
    assert planned.mission.plan["servo_start_positions"] == 3


def test_that_the_worst_coverage_is_the_lowest_start_position_s():
    m = Mission(SMALL, p_traj=0.3, altitude_m=6.0)
    wfs = [named_waveform("semi-triangular", 5.0, k) for k in (0, 3, 7, 12)]
    each = [predict_coverage(m, wf, LIDAR, LIDARLITE_V3.rate_hz).predicted_ra_pct for wf in wfs]
    target = CoverageTarget(1.0, wfs[0], LIDAR, LIDARLITE_V3.rate_hz, also_waveforms=tuple(wfs[1:]))
    assert len(set(each)) > 1  # the start position matters at this offset
    assert worst_coverage(m, target).predicted_ra_pct == pytest.approx(min(each))


def test_that_the_planner_refuses_when_the_rangefinder_cannot_reach_the_floor():
    target = CoverageTarget(99.0, WF, RangeLimit(5.0), LIDARLITE_V3.rate_hz)
    with pytest.raises(ValueError, match=r"reaches no floor from 7\.9 m") as e:
        plan_coverage(SMALL, target, altitude_m=8.0)
    assert "\n" not in str(e.value)


def test_that_the_planner_refuses_a_building_wider_than_a_loop_can_cover():
    target = CoverageTarget(99.0, WF, RangeLimit(12.0), LIDARLITE_V3.rate_hz)  # 1.5 m reach from 11.9 m
    with pytest.raises(ValueError, match="lawnmower"):
        plan_coverage(Storage(), target)


@pytest.mark.parametrize("bad", [dict(waypoints=((1, 1), (5, 1), (5, 5), (1, 5))),  # not closed
                                 dict(waypoints=((0.2, 1), (5, 1), (5, 5), (0.2, 1))),  # too near a wall
                                 dict(waypoints=((1, 1), (1, 1), (5, 5), (1, 1)))])  # repeated waypoint
def test_that_a_malformed_loop_is_refused(bad):
    with pytest.raises(ValueError):
        LoopMission(storage=SMALL, altitude_m=6.0, **bad)


def test_that_a_coverage_loop_exports_to_qgc_wpl_and_back_to_the_millimetre(tmp_path):
    m = LoopPlan((2.0, 3.0, 4.0, 5.0), corner_cut_m=1.5, speed_m_s=1.5).mission(SMALL, 6.0, math.radians(30))
    frame = StorageFrame((0.0, 0.0, 0.0), math.radians(25))
    rows = read_qgc_wpl(write_qgc_wpl(tmp_path / "c.waypoints", m, frame))
    nav = [r for r in rows if int(r[3]) == mavlink.MAV_CMD_NAV_WAYPOINT][1:]
    lat0, lon0, _ = DEFAULT_ORIGIN
    got = np.array([global_to_ned(r[8], r[9], lat0, lon0) for r in nav])
    wp = m.waypoints_w()
    expected = frame.w_to_ned(np.column_stack([wp[1:], np.zeros(len(wp) - 1)]))[:, :2]
    assert len(wp) == 9  # four corners cut in two, and the first again
    assert np.abs(got - expected).max() < 1e-3
    speed = [r for r in rows if int(r[3]) == mavlink.MAV_CMD_DO_CHANGE_SPEED]
    assert speed[0][5] == 1.5


def test_that_plan_writes_a_coverage_plan(tmp_path, capsys):
    out = tmp_path / "cov.waypoints"
    assert main(["plan", "--coverage", "95", "--storage", "30x20x10", "--altitude", "6", "--out", str(out)]) == 0
    assert "predicted R_a" in capsys.readouterr().out
    assert len(read_qgc_wpl(out)) >= 8


def test_that_plan_all_phases_plans_for_every_servo_start_position(tmp_path, capsys, monkeypatch):
    import dataclasses

    import sitl.missions.coverage as coverage
    seen = []

    def quick(storage, target, **kw):  # the real planner on two of the positions and one speed: the full search is slow
        seen.append(target)
        return plan_coverage(storage, dataclasses.replace(target, also_waveforms=target.also_waveforms[:1],
                                                          speeds_m_s=(2.0,)), **kw)

    monkeypatch.setattr(coverage, "plan_coverage", quick)
    out = tmp_path / "cov.waypoints"
    assert main(["plan", "--coverage", "95", "--all-phases", "--storage", "30x20x10", "--altitude", "6",
                 "--out", str(out)]) == 0
    assert "worst of 20 servo start positions" in capsys.readouterr().out
    wfs = {seen[0].waveform, *seen[0].also_waveforms}
    assert wfs == {named_waveform("semi-triangular", 5.0, k) for k in range(20)} and len(wfs) == 20
    assert len(read_qgc_wpl(out)) >= 8


@pytest.mark.parametrize("argv, message", [
    (["plan"], "needs --p-traj"),
    (["plan", "--coverage", "99", "--rangefinder", "tfmini"], "lawnmower"),
    (["plan", "--coverage", "120"], "target coverage must be in (0, 100]"),
    (["plan", "--coverage", "99", "--altitude", "20"], "altitude 20 m does not fit"),
    (["fly", "--stockpile", "1", "--coverage", "99"], "add --mission coverage"),
    (["plan", "--p-traj", "20", "--all-phases"], "shape a coverage plan: add --coverage PCT"),
    (["fly", "--stockpile", "1", "--p-traj", "20", "--surface", "r"], "add --coverage PCT and --mission coverage"),
])
def test_that_plan_refuses_with_one_line(tmp_path, capsys, argv, message):
    assert main([*argv, "--out", str(tmp_path / "x.waypoints")]) != 0
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1


def test_that_fly_coverage_needs_a_target(tmp_path, capsys):
    assert main(["fly", "--stockpile", "1", "--mission", "coverage", "--plant", "ideal",
                 "--out", str(tmp_path / "r")]) != 0
    assert "needs --coverage" in capsys.readouterr().err


def test_that_fly_flies_the_coverage_plan_and_records_it(tmp_path):
    import json
    out = tmp_path / "run"
    assert main(["fly", "--stockpile", "1", "--mission", "coverage", "--coverage", "95", "--plant", "ideal",
                 "--out", str(out), "--quiet"]) == 0
    truth = json.loads((out / "truth.json").read_text())
    assert truth["mission"]["kind"] == "coverage"
    assert truth["mission"]["plan"]["predicted_ra_pct"] >= 95
    wp = np.asarray(truth["mission"]["waypoints"])
    nav = [r for r in read_qgc_wpl(out / "mission.waypoints") if int(r[3]) == mavlink.MAV_CMD_NAV_WAYPOINT][1:]
    assert len(nav) == len(wp) - 1
