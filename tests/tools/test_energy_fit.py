"""tools.energy_fit: the energy model's fit from flights (here made by a known model: no JSBSim)."""

import math

import pytest

from sitl.missions.coverage import EnergyModel, loop_turns_rad
from tools import energy_fit as ef


def _flights(model: EnergyModel) -> list[ef.Flight]:
    out = []
    missions = {**ef.fit_missions(), **ef.held_out_missions()}
    for i, (name, m) in enumerate(missions.items()):
        turns = tuple(loop_turns_rad(m.waypoints_w()))
        t = model.flight_time_s(m.path_length_m(), m.speed_m_s, turns, m.yaw_rate_max_rad_s)
        plain = len(turns) == 4
        out.append(ef.Flight(name, "fit" if i % 3 else "held-out", m.path_length_m(), m.speed_m_s,
                             m.yaw_rate_max_rad_s, turns, t, model.power_w * t,
                             model.overshoot_m(m.speed_m_s) if plain else None))
    return out


def test_that_the_fit_recovers_the_model_that_made_the_flights():
    truth = EnergyModel(power_w=150.0, leg_factor=1.01, turn_factor=0.6, reverse_factor=0.9, stop_s_per_m_s=0.7,
                        waypoint_s=0.8, brake_m_s2=2.5)
    got = ef.fit(_flights(truth))
    for name in ("power_w", "leg_factor", "turn_factor", "reverse_factor", "stop_s_per_m_s", "waypoint_s",
                 "brake_m_s2"):
        assert getattr(got, name) == pytest.approx(getattr(truth, name), rel=1e-6), name


def test_that_the_fit_and_held_out_sets_hold_sharp_turns_and_every_yaw_rate_checked():
    fit = ef.fit_missions()
    turns = [max(loop_turns_rad(m.waypoints_w())) for m in fit.values()]
    assert max(turns) == pytest.approx(math.pi)  # out and back: the reverse term is fitted, not extrapolated
    assert any(math.pi / 2 + 0.1 < t < math.pi - 0.1 for t in turns)
    yaws = {round(math.degrees(m.yaw_rate_max_rad_s)) for m in ef.held_out_missions().values()}
    assert yaws == {30, 17, 6, 1}
