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
    NEAR_WALL_STEPS,
    CoverageTarget,
    EnergyModel,
    LoopMission,
    LoopPlan,
    WallBand,
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


def test_that_a_small_building_gets_a_loop_though_the_familys_first_offsets_lie_within_the_clearance():
    """12 x 8 m: 5 % of the width is 0.4 m, inside the 0.5 m clearance; every loop began there and was refused,
    and the planner said "best 0.0 %". The offsets within the clearance are left out of the ladder instead."""
    from sitl.runners.fly import legs_room_m
    target = CoverageTarget(95.0, WF, LIDAR, LIDARLITE_V3.rate_hz, speeds_m_s=(1.0,))
    small = Storage(12.0, 8.0, 6.0)
    planned = plan_coverage(small, target, altitude_m=5.0)
    assert planned.coverage.predicted_ra_pct >= 95.0
    assert legs_room_m(planned.mission) >= planned.mission.min_clearance_m


def test_that_a_target_missed_by_hundredths_is_not_said_to_have_been_reached():
    """The best loop predicts 99.96 %: the refusal said "best 100.0 %" for a 100 % target."""
    target = CoverageTarget(100.0, WF, LIDAR, LIDARLITE_V3.rate_hz, speeds_m_s=(1.0,))
    with pytest.raises(ValueError, match=r"no loop reaches 100 % predicted coverage \(best 99\.\d\d %") as e:
        plan_coverage(SMALL, target, altitude_m=9.0)
    assert "100.0" not in str(e.value)


def test_that_a_long_plan_says_how_far_it_got(caplog):
    """Planned on an earlier survey's surface for every servo start position, a plan takes minutes (3.5 s a loop,
    hundreds of loops): the planner reports each loop it evaluated, and the CLI says so every PROGRESS_EVERY_S."""
    from sitl.cli import planning_progress
    seen = []
    target = CoverageTarget(97.0, WF, LIDAR, LIDARLITE_V3.rate_hz, speeds_m_s=(2.0,))
    planned = plan_coverage(SMALL, target, altitude_m=6.0, progress=lambda n, best: seen.append((n, best)))
    assert [n for n, _ in seen] == list(range(1, len(seen) + 1)) and len(seen) == planned.n_evaluated
    assert max(b for _, b in seen) >= planned.coverage.predicted_ra_pct >= 97.0
    now = [0.0]
    say = planning_progress(every_s=10.0, clock=lambda: now[0])
    with caplog.at_level("INFO", logger="sitl.cli"):
        for n in range(1, 7):
            now[0] = 4.0 * n  # a loop every 4 s: a line at 12 s, the next 10 s later or after (24 s)
            say(n, 90.0 + n)
    lines = [r.getMessage() for r in caplog.records]
    assert lines == ["coverage plan: 3 loops evaluated in 12 s, the best predicts 93.00 % so far",
                     "coverage plan: 6 loops evaluated in 24 s, the best predicts 96.00 % so far"]


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
    expected = frame.w_to_ned(np.column_stack([wp, np.zeros(len(wp))]))[:, :2]  # W0 first after the take-off
    assert len(wp) == 9  # four corners cut in two, and the first again
    assert np.abs(got - expected).max() < 1e-3
    speed = [r for r in rows if int(r[3]) == mavlink.MAV_CMD_DO_CHANGE_SPEED]
    assert speed[0][5] == 1.5


def test_that_plan_writes_a_coverage_plan(tmp_path, capsys, one_speed):
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
    (["plan", "--p-traj", "20", "--bare-walls"], "shape a coverage plan: add --coverage PCT"),
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


def test_that_fly_flies_the_coverage_plan_and_records_it(tmp_path, one_speed):
    import json
    out = tmp_path / "run"
    assert main(["fly", "--stockpile", "1", "--mission", "coverage", "--coverage", "95", "--plant", "ideal",
                 "--storage", "30x20x10", "--altitude", "9",  # a small building: the planning is the cost
                 "--out", str(out), "--quiet"]) == 0
    truth = json.loads((out / "truth.json").read_text())
    assert truth["mission"]["kind"] == "coverage"
    assert truth["mission"]["plan"]["predicted_ra_pct"] >= 95
    wp = np.asarray(truth["mission"]["waypoints"])
    nav = [r for r in read_qgc_wpl(out / "mission.waypoints") if int(r[3]) == mavlink.MAV_CMD_NAV_WAYPOINT][1:]
    assert len(nav) == len(wp)  # W0 first after the take-off, then the loop


# ----- the energy model with the autopilot's stops, and material leaning on the walls (issue 17 item 1) -----

YAW_30 = math.radians(30)


def test_that_each_waypoint_costs_a_stop_that_grows_with_the_speed():
    e = EnergyModel()
    square, cut = [math.pi / 2] * 4, [math.pi / 4] * 8  # the same heading change in all, stops at more waypoints
    for v in (0.5, 2.0):
        assert e.energy_j(100.0, v, square, YAW_30) > e.energy_j(100.0, v, [0.0] * 4 + square[:0], YAW_30)
    extra = [e.energy_j(100.0, v, [math.pi / 2] * 8, YAW_30) - e.energy_j(100.0, v, square, YAW_30)
             for v in (0.5, 2.0)]
    assert extra[1] > extra[0] > 0  # braking from 2 m/s costs more than from 0.5 m/s
    assert e.energy_j(100.0, 2.0, cut, YAW_30) != e.energy_j(100.0, 2.0, square, YAW_30)


def test_that_a_slower_yaw_rate_costs_more_energy_for_the_same_loop():
    m30 = Mission(p_traj=0.2)
    m6 = Mission(p_traj=0.2, yaw_rate_max_rad_s=math.radians(6))
    assert mission_energy_j(m6) > mission_energy_j(m30) + 4 * 0.5 * EnergyModel().power_w  # >= 2 s a corner more


def test_that_the_overshoot_grows_with_the_square_of_the_speed():
    e = EnergyModel()
    assert e.overshoot_m(2.0) == pytest.approx(4 * e.overshoot_m(1.0))
    assert 0.3 < e.overshoot_m(2.0) < 1.5  # what the JSBSim F450 ran past its corners (tools.energy_fit)


def test_that_the_wall_band_is_the_ground_stations():
    from ground.pointcloud import Cloud, SensorErrorModel, plane_tolerances_m, structure_n_sigma
    from sitl.missions import coverage
    rng = np.random.default_rng(3)
    d = rng.normal(size=(50, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    r = rng.uniform(1.0, 30.0, 50)
    cloud = Cloud(points_w=np.zeros((50, 3)), dirs_w=d, range_m=r, path_w=np.zeros((1, 3)), n_samples=50,
                  n_excluded=0)
    err = SensorErrorModel(LIDARLITE_V3.range_sigma_m, LIDARLITE_V3.range_sigma_rel, LIDARLITE_V3.resolution_m, 0.02)
    band = WallBand.of(LIDARLITE_V3, position_sigma_m=0.02)
    assert np.allclose(band.tolerances_m(r, d, 50), plane_tolerances_m(cloud, err))
    for n in (0, 10, 40_000, 10**7):
        assert coverage.structure_n_sigma(n) == pytest.approx(structure_n_sigma(n))


def test_that_material_at_the_walls_costs_a_far_leg_its_row_of_cells_and_a_near_leg_nothing():
    band = WallBand.of(LIDARLITE_V3)
    rate = LIDARLITE_V3.rate_hz
    far = LoopPlan((2.0, 6.0, 2.0, 6.0), 0.0, 2.0).mission(Storage(), 12.0, YAW_30)  # east and west legs 6 m off
    near = LoopPlan((1.5, 1.5, 1.5, 1.5), 0.0, 2.0).mission(Storage(), 12.0, YAW_30)
    far_bare, far_banded = (predict_coverage(far, WF, LIDAR, rate, walls=w) for w in (None, band))
    near_bare, near_banded = (predict_coverage(near, WF, LIDAR, rate, walls=w) for w in (None, band))
    assert near_bare.predicted_ra_pct - near_banded.predicted_ra_pct < 0.05
    lost = far_banded.covered != far_bare.covered
    nx, ny = lost.shape
    ix, iy = lost.nonzero()
    to_wall = np.minimum.reduce([ix, nx - 1 - ix, iy, ny - 1 - iy])
    assert (lost[0].sum() + lost[-1].sum()) >= 0.9 * 2 * ny  # (nearly) the whole outer row along east and west
    assert (to_wall <= 1).mean() > 0.9  # the walls' foot, and a little more where the hull cuts the corners
    assert to_wall.max() * 0.25 <= 1.0


def test_that_the_planner_flies_nearer_the_walls_than_5_percent_when_they_may_carry_material():
    s = Storage()
    bare = CoverageTarget(99.8, WF, LIDAR, LIDARLITE_V3.rate_hz, speeds_m_s=(2.0,))
    walls = CoverageTarget(99.8, WF, LIDAR, LIDARLITE_V3.rate_hz, speeds_m_s=(2.0,), walls=WallBand.of(LIDARLITE_V3))
    planned = plan_coverage(s, walls)
    sizes = (s.width_m, s.length_m, s.width_m, s.length_m)
    assert all(o <= 0.05 * z + 1e-9 for o, z in zip(planned.plan.offsets_m, sizes, strict=True))
    assert any(o < 0.05 * z - 1e-9 for o, z in zip(planned.plan.offsets_m, sizes, strict=True))
    assert min(planned.plan.offsets_m) >= 0.5 + EnergyModel().overshoot_m(2.0)  # clearance plus the overshoot
    assert planned.mission.plan["material_at_walls"] is True
    assert plan_coverage(s, bare).plan.offsets_m != planned.plan.offsets_m


def test_that_the_near_wall_steps_lie_below_the_familys_nearest():
    assert max(NEAR_WALL_STEPS) < 0.05 and min(NEAR_WALL_STEPS) > 0


@pytest.mark.parametrize("flag, walls", [([], True), (["--bare-walls"], False)])
def test_that_plan_assumes_material_on_the_walls_unless_told_they_are_bare(flag, walls, tmp_path, one_speed):
    seen = one_speed
    assert main(["plan", "--coverage", "95", "--storage", "30x20x10", "--altitude", "6", *flag,
                 "--out", str(tmp_path / "c.waypoints")]) == 0
    assert (seen[0].walls == WallBand.of(LIDARLITE_V3)) if walls else seen[0].walls is None


def test_that_on_a_surveyed_surface_the_band_drops_material_at_a_wall_and_keeps_bare_floor():
    from sitl.missions.surveyed_surface import HeightField
    s = Storage()
    heights = np.zeros((240, 160))
    heights[-8:, :] = 2.0  # a 2 m bank against the east wall (x = L); the west wall's foot is bare floor
    surface = HeightField(heights, s.length_m, s.width_m)
    m = LoopPlan((2.0, 4.0, 2.0, 4.0), 0.0, 2.0).mission(s, 12.0, YAW_30)
    band = WallBand.of(LIDARLITE_V3)
    rate = LIDARLITE_V3.rate_hz
    bare = floor_hits_w(m, WF, LIDAR, rate, surface=surface)
    kept = floor_hits_w(m, WF, LIDAR, rate, surface=surface, walls=band)
    assert (kept[:, 0] > s.length_m - 0.1).sum() < (bare[:, 0] > s.length_m - 0.1).sum() / 2  # the bank's edge
    assert (kept[:, 0] < 0.1).sum() == (bare[:, 0] < 0.1).sum() > 0  # the floor at the bare wall stays
