import math

import pytest

from sitl.sensing.pose_drift import PoseErrorProfile, ekf_source_params
from sitl.vehicle.api import CommandRejected, FlightMode, NavItem, NavKind, VehicleState
from sitl.vehicle.kinematic_vehicle import KinematicVehicle, wrap_pi

ALT_M = 2.0
RECTANGLE = [(1.0, 1.0), (5.0, 1.0), (5.0, 4.0), (1.0, 4.0)]


def fast_vehicle(**kw) -> KinematicVehicle:
    args = dict(speed_m_s=2.0, yaw_rate_max_rad_s=math.radians(90), altitude_m=ALT_M, climb_rate_m_s=2.0)
    args.update(kw)
    return KinematicVehicle(**args)


def survey_items(land: bool = True) -> list[NavItem]:
    items = [NavItem(NavKind.TAKEOFF, 0.0, 0.0, -ALT_M)]
    items += [NavItem(NavKind.WAYPOINT, n, e, -ALT_M) for n, e in RECTANGLE]
    if land:
        items.append(NavItem(NavKind.LAND, 0.0, 0.0, 0.0))
    return items


def run(v: KinematicVehicle, until, max_s: float = 60.0) -> list[VehicleState]:
    """Step until until(state) holds; the states seen, the last one satisfying it."""
    states = []
    for _ in range(round(max_s / v.dt_s)):
        v.step()
        states.append(v.state())
        if until(states[-1]):
            return states
    raise AssertionError(f"condition not met within {max_s} s of simulated time")


def start_auto(v: KinematicVehicle, items: list[NavItem]) -> None:
    v.load_mission(items)
    v.arm()
    v.set_mode(FlightMode.AUTO)


def test_that_a_new_vehicle_is_landed_disarmed_in_stabilize_on_the_floor_at_home():
    v = KinematicVehicle(home_ned_m=(3.0, -2.0, 0.0))
    s = v.state()
    assert (s.t_s, s.pos_ned_m, s.armed, s.landed, s.mode) == (0.0, (3.0, -2.0, 0.0), False, True,
                                                               FlightMode.STABILIZE)
    assert v.current_item() == -1 and v.pop_reached() == []


def test_that_a_home_off_the_floor_is_refused():
    with pytest.raises(ValueError, match="floor"):
        KinematicVehicle(home_ned_m=(0.0, 0.0, -1.0))


def test_that_params_are_exactly_speed_yaw_rate_in_degrees_altitude_and_the_ekf_sources_of_an_exact_pose():
    v = KinematicVehicle(speed_m_s=1.5, yaw_rate_max_rad_s=math.radians(45), altitude_m=9.0)
    assert v.params == pytest.approx({"PS_SPEED_MS": 1.5, "PS_YAW_RATE_DPS": 45.0, "PS_ALT_M": 9.0,
                                      **ekf_source_params(PoseErrorProfile.NONE)})
    assert all(type(value) is float for value in v.params.values())
    with pytest.raises(ValueError, match="read-only"):
        v.set_param("EK3_SRC1_POSZ", 2.0)


def test_that_set_param_refuses_unknown_names_with_key_error():
    v = KinematicVehicle()
    with pytest.raises(KeyError):
        v.set_param("WPNAV_SPEED", 3.0)
    assert "WPNAV_SPEED" not in v.params


@pytest.mark.parametrize(("name", "value"), [("PS_SPEED_MS", 0.01), ("PS_SPEED_MS", 16.0), ("PS_SPEED_MS", math.nan),
                                             ("PS_YAW_RATE_DPS", 0.0), ("PS_YAW_RATE_DPS", 400.0),
                                             ("PS_ALT_M", 0.2), ("PS_ALT_M", math.inf)])
def test_that_set_param_refuses_nan_and_out_of_range_values_naming_the_value(name, value):
    v = KinematicVehicle()
    before = dict(v.params)
    with pytest.raises(ValueError, match=str(value)):
        v.set_param(name, value)
    assert v.params == before


def test_that_set_param_accepts_the_range_ends():
    v = KinematicVehicle()
    v.set_param("PS_SPEED_MS", 15.0)
    v.set_param("PS_YAW_RATE_DPS", 0.1)
    assert (v.params["PS_SPEED_MS"], v.params["PS_YAW_RATE_DPS"]) == (15.0, 0.1)


def test_that_arm_needs_a_disarmed_vehicle_and_an_armable_mode():
    v = KinematicVehicle()
    v.arm()
    assert v.state().armed
    with pytest.raises(CommandRejected, match="already armed"):
        v.arm()
    v.disarm()
    v.set_mode(FlightMode.LAND)
    with pytest.raises(CommandRejected, match="LAND"):
        v.arm()


def test_that_guided_takeoff_climbs_vertically_at_the_climb_rate_and_hovers():
    v = fast_vehicle(climb_rate_m_s=1.0)
    v.set_mode(FlightMode.GUIDED)
    v.arm()
    v.takeoff(3.0)
    states = run(v, lambda s: s.pos_ned_m[2] <= -3.0 + 1e-9)
    assert states[-1].t_s == pytest.approx(3.0, abs=v.dt_s)
    assert all(s.pos_ned_m[:2] == (0.0, 0.0) for s in states)
    assert max(abs(s.vel_ned_m_s[2]) for s in states) == pytest.approx(1.0)
    assert not states[-1].landed
    hover = run(v, lambda s: s.t_s >= 5.0)
    assert hover[-1].pos_ned_m == (0.0, 0.0, -3.0) and hover[-1].vel_ned_m_s == (0.0, 0.0, 0.0)


@pytest.mark.parametrize(("setup", "alt", "reason"), [
    ("stabilize", 3.0, "GUIDED"), ("disarmed", 3.0, "armed"), ("guided", 0.4, "0.4"), ("guided", math.nan, "nan"),
    ("flying", 3.0, "landed")])
def test_that_takeoff_needs_guided_armed_landed_and_at_least_half_a_metre(setup, alt, reason):
    v = fast_vehicle()
    if setup != "stabilize":
        v.set_mode(FlightMode.GUIDED)
    if setup != "disarmed":
        v.arm()
    if setup == "flying":
        v.takeoff(1.0)
        run(v, lambda s: not s.landed)
    with pytest.raises(CommandRejected, match=reason):
        v.takeoff(alt)


def test_that_auto_needs_a_mission_and_an_armed_vehicle():
    v = fast_vehicle()
    v.arm()
    with pytest.raises(CommandRejected, match="no mission"):
        v.set_mode(FlightMode.AUTO)
    with pytest.raises(CommandRejected, match="no mission"):
        v.start_mission()
    v.disarm()
    v.load_mission(survey_items())
    with pytest.raises(CommandRejected, match="arm"):
        v.set_mode(FlightMode.AUTO)
    assert v.state().mode is FlightMode.STABILIZE


def test_that_rtl_is_not_supported():
    with pytest.raises(CommandRejected, match="RTL"):
        KinematicVehicle().set_mode(FlightMode.RTL)


def test_that_a_waypoint_is_flown_by_turning_in_place_within_the_yaw_limit_then_straight_at_speed():
    v = fast_vehicle(yaw_rate_max_rad_s=math.radians(30), speed_m_s=1.5)
    start_auto(v, [NavItem(NavKind.TAKEOFF, 0, 0, -ALT_M), NavItem(NavKind.WAYPOINT, -3.0, 4.0, -ALT_M)])
    run(v, lambda s: v.current_item() == 1)
    states = run(v, lambda s: v.current_item() == -1)
    bearing = math.atan2(4.0, -3.0)
    turning = [s for s in states if s.vel_ned_m_s == (0.0, 0.0, 0.0)]
    flying = [s for s in states if s.vel_ned_m_s != (0.0, 0.0, 0.0)]
    # the turn: in place, at no more than the yaw-rate limit, ending within 1 deg of the bearing
    assert all(s.pos_ned_m[:2] == (0.0, 0.0) for s in turning)
    assert max(abs(s.yawspeed_rad_s) for s in states) <= math.radians(30) * (1 + 1e-9)
    assert turning[-1].t_s - turning[0].t_s == pytest.approx(abs(bearing) / math.radians(30), abs=0.05)
    assert abs(wrap_pi(turning[-1].yaw_rad - bearing)) < math.radians(1)
    # the leg: straight along the bearing at speed, at the altitude (take-off is reached within 0.1 m)
    for s in flying:
        n, e, d = s.pos_ned_m
        assert abs(-n * math.sin(bearing) + e * math.cos(bearing)) < 1e-9
        assert math.hypot(*s.vel_ned_m_s[:2]) <= 1.5 + 1e-9 and abs(d + ALT_M) <= 0.1
    assert math.hypot(*flying[len(flying) // 2].vel_ned_m_s[:2]) == pytest.approx(1.5)
    assert math.dist(states[-1].pos_ned_m, (-3.0, 4.0, -ALT_M)) <= 0.1


def test_that_altitude_changes_linearly_along_a_leg_to_the_next_waypoint_height():
    v = fast_vehicle(speed_m_s=1.0, climb_rate_m_s=1.0)
    start_auto(v, [NavItem(NavKind.TAKEOFF, 0, 0, -2.0), NavItem(NavKind.WAYPOINT, 8.0, 0.0, -4.0)])
    run(v, lambda s: v.current_item() == 1)
    flying = [s for s in run(v, lambda s: v.current_item() == -1) if s.vel_ned_m_s != (0.0, 0.0, 0.0)]
    n0, _, d0 = flying[0].pos_ned_m
    slope = (-4.0 - d0) / (8.0 - n0)
    assert all(s.pos_ned_m[2] == pytest.approx(d0 + slope * (s.pos_ned_m[0] - n0), abs=1e-9) for s in flying)


def test_that_a_waypoint_straight_above_is_climbed_to_without_turning():
    v = fast_vehicle(climb_rate_m_s=0.5)
    start_auto(v, [NavItem(NavKind.TAKEOFF, 0, 0, -1.0), NavItem(NavKind.WAYPOINT, 0.0, 0.0, -3.0)])
    states = run(v, lambda s: v.current_item() == -1)
    assert all(s.yaw_rad == 0.0 for s in states)
    assert max(abs(s.vel_ned_m_s[2]) for s in states) == pytest.approx(0.5)


def test_that_every_item_is_reached_in_order_and_the_land_item_lands_and_disarms():
    v = fast_vehicle()
    start_auto(v, survey_items(land=True))
    reached, currents = [], set()

    def done(s):
        reached.extend(v.pop_reached())
        currents.add(v.current_item())
        return not s.armed

    states = run(v, done)
    assert reached == [0, 1, 2, 3, 4, 5]
    assert currents == {-1, 0, 1, 2, 3, 4, 5}
    last = states[-1]
    assert last.landed and last.pos_ned_m[2] == 0.0 and v.current_item() == -1
    assert math.dist(last.pos_ned_m[:2], RECTANGLE[-1]) <= 0.1  # lands where it is
    assert "mission complete" in v.pop_status_text()
    descent = [s for s in states if s.vel_ned_m_s[2] > 0]
    assert max(s.vel_ned_m_s[2] for s in descent) == pytest.approx(2.0)


def test_that_each_waypoint_is_passed_within_the_acceptance_radius():
    v = fast_vehicle()
    start_auto(v, survey_items(land=False))
    positions = {}

    def done(s):
        for i in v.pop_reached():
            positions[i] = s.pos_ned_m
        return s.mode is FlightMode.LOITER

    run(v, done)
    for i, (n, e) in enumerate(RECTANGLE, start=1):
        assert math.dist(positions[i], (n, e, -ALT_M)) <= 0.1


def test_that_after_the_last_waypoint_it_hovers_in_loiter_and_reports_mission_complete():
    v = fast_vehicle()
    start_auto(v, survey_items(land=False))
    end = run(v, lambda s: s.mode is FlightMode.LOITER)[-1]
    assert "mission complete" in v.pop_status_text() and v.current_item() == -1
    later = run(v, lambda s: s.t_s >= end.t_s + 2.0)[-1]
    assert later.armed and later.pos_ned_m == end.pos_ned_m and later.vel_ned_m_s == (0.0, 0.0, 0.0)


def test_that_a_takeoff_item_without_altitude_climbs_to_ps_alt_m():
    v = fast_vehicle(altitude_m=3.5)
    start_auto(v, [NavItem(NavKind.TAKEOFF, 0, 0, 0.0)])
    assert run(v, lambda s: s.mode is FlightMode.LOITER)[-1].pos_ned_m[2] == pytest.approx(-3.5, abs=0.1)


def test_that_the_mission_cannot_be_replaced_while_flying_it_in_auto_but_can_after():
    v = fast_vehicle()
    start_auto(v, survey_items(land=False))
    run(v, lambda s: not s.landed)
    with pytest.raises(CommandRejected, match="AUTO"):
        v.load_mission([])
    v.set_mode(FlightMode.LOITER)
    v.load_mission([NavItem(NavKind.LAND, 0, 0, 0)])
    v.set_mode(FlightMode.AUTO)
    assert v.current_item() == 0


def test_that_leaving_auto_pauses_the_mission_and_reentering_resumes_the_same_item():
    v = fast_vehicle()
    start_auto(v, survey_items())
    run(v, lambda s: v.current_item() == 2)
    v.set_mode(FlightMode.LOITER)
    assert v.current_item() == -1
    paused = v.state().pos_ned_m
    assert run(v, lambda s: s.t_s > 20)[-1].pos_ned_m == paused
    v.set_mode(FlightMode.AUTO)
    assert v.current_item() == 2


def test_that_start_mission_restarts_from_item_zero():
    v = fast_vehicle()
    start_auto(v, survey_items(land=False))
    run(v, lambda s: v.current_item() == 3)
    v.start_mission()
    assert v.current_item() == 0 and v.state().mode is FlightMode.AUTO


def test_that_disarm_in_flight_is_refused_unless_forced_and_a_forced_disarm_drops_to_the_floor():
    v = fast_vehicle()
    start_auto(v, survey_items())
    run(v, lambda s: v.current_item() == 2)
    with pytest.raises(CommandRejected, match="in flight"):
        v.disarm()
    assert v.state().armed
    n, e, _ = v.state().pos_ned_m
    v.disarm(force=True)
    s = v.state()
    assert (s.armed, s.landed, s.pos_ned_m, s.vel_ned_m_s) == (False, True, (n, e, 0.0), (0.0, 0.0, 0.0))
    v.step()
    assert v.state().pos_ned_m == (n, e, 0.0) and v.current_item() == -1


def test_that_energy_is_hover_power_plus_twenty_watts_per_metre_per_second_and_the_voltage_sags():
    v = fast_vehicle(speed_m_s=2.0)
    v.set_mode(FlightMode.GUIDED)
    v.arm()
    run(v, lambda s: s.t_s >= 1.0)
    assert v.state().energy_j == 0.0 and v.state().battery_voltage_v == 16.0  # idle on the floor
    v.takeoff(2.0)
    run(v, lambda s: s.pos_ned_m[2] <= -2.0)  # 1 s at 2 m/s: (180 + 40) W
    e_climb = v.state().energy_j
    assert e_climb == pytest.approx(220.0, abs=220 * v.dt_s)
    t0 = v.state().t_s
    run(v, lambda s: s.t_s >= t0 + 10.0)  # 10 s hover: 1800 J
    s = v.state()
    assert s.energy_j - e_climb == pytest.approx(1800.0, rel=1e-6)
    assert 15.9 < s.battery_voltage_v < 16.0


def test_that_a_speed_change_takes_effect_mid_leg():
    v = fast_vehicle(speed_m_s=1.0)
    start_auto(v, [NavItem(NavKind.TAKEOFF, 0, 0, -ALT_M), NavItem(NavKind.WAYPOINT, 20.0, 0.0, -ALT_M)])
    run(v, lambda s: s.vel_ned_m_s[0] > 0 and s.pos_ned_m[0] > 1.0)
    v.set_param("PS_SPEED_MS", 4.0)
    v.step()
    assert v.state().vel_ned_m_s[0] == pytest.approx(4.0)


def test_that_the_yaw_rate_parameter_limits_the_turn_rate():
    v = fast_vehicle()
    v.set_param("PS_YAW_RATE_DPS", 10.0)
    start_auto(v, [NavItem(NavKind.TAKEOFF, 0, 0, -ALT_M), NavItem(NavKind.WAYPOINT, 0.0, 5.0, -ALT_M)])
    states = run(v, lambda s: v.current_item() == -1)
    assert max(abs(s.yawspeed_rad_s) for s in states) == pytest.approx(math.radians(10.0))


def test_that_two_runs_are_identical():
    def flight():
        v = fast_vehicle()
        start_auto(v, survey_items())
        return run(v, lambda s: not s.armed)

    assert flight() == flight()


def test_that_load_mission_refuses_things_that_are_not_nav_items():
    with pytest.raises(TypeError, match="NavItem"):
        KinematicVehicle().load_mission([(0.0, 0.0, -1.0)])
