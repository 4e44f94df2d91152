"""The TFMini campaign's mission and piles: chosen from the range at the surfaces' reflectance, low enough
to reach the floor along the walls, high enough to clear the piles."""

import math

import pytest

from firmware_py.core.sensor import TFMINI_S
from firmware_py.core.storage import Storage
from sitl.missions.range_check import check_range, planning_limit, range_coverage
from sitl.world.stockpile import load_mesh, paper_pile
from tools import tfmini_campaign as camp
from tools.make_two_lobe_pile import DEFAULT_OUT as TWO_LOBE

STORAGE = Storage.parse(camp.STORAGE)
LIMIT = planning_limit(TFMINI_S, "datasheet")


def test_that_the_campaigns_p_traj_is_the_largest_keeping_every_leg_within_the_floors_reach_of_its_wall():
    m = camp.mission()
    reach = range_coverage(m, LIMIT, camp.WF).floor_reach_m
    assert m.p_traj * STORAGE.length_m <= reach and m.p_traj * STORAGE.width_m <= reach
    assert (m.p_traj + 0.01) * STORAGE.length_m > reach


def test_that_the_campaigns_mission_is_flown_and_the_old_9_m_one_is_refused_with_datasheet_noise():
    m = camp.mission()
    check_range(m, LIMIT, camp.WF)  # flown (a warning about the middle of an empty bay at most)
    with pytest.raises(ValueError, match="out of reach: all of the floor"):
        check_range(type(m)(storage=STORAGE, p_traj=0.20, altitude_m=9.0), LIMIT, camp.WF)


def test_that_the_campaigns_piles_are_the_test_piles_at_half_height_under_the_flight(tmp_path):
    piles = camp.make_piles(tmp_path)
    pile1, lobes = (load_mesh(p, STORAGE) for p in piles.values())
    assert pile1.volume_m3 == pytest.approx(camp.PILE_SCALE * paper_pile("1", STORAGE).volume_m3, rel=1e-5)
    assert lobes.volume_m3 == pytest.approx(camp.PILE_SCALE * load_mesh(TWO_LOBE, STORAGE).volume_m3, rel=1e-5)
    for pile in (pile1, lobes):
        assert camp.mission().altitude_m - pile.max_height_m >= camp.TOP_CLEARANCE_M
    again = camp.make_piles(tmp_path / "again")  # deterministic: the same bytes each run
    for a, b in zip(piles.values(), again.values(), strict=True):
        assert a.read_bytes() == b.read_bytes()


def test_that_the_page_shows_the_measured_figures_and_the_check_verdicts():
    run = {"ve_pct": 1.25, "ra_pct": 97.0, "samples": 9000, "points": 5000, "lowest_m": 4.97}
    results = {"pile X": {"top_m": 3.6, "true_volume_m3": 850.0,
                          "lockstep": {"none": [dict(run, ve_pct=0.03)], "datasheet": [run]},
                          "networked": {"none": dict(run, ve_pct=0.05), "datasheet": dict(run, ve_pct=2.5)}}}
    text = camp.page(results, [0])
    assert "| pile X | 3.60 | 850.0 | 0.03 | 1.25 | 97.00 | 0.05 (9,000 samples) | 2.50 (9,000 samples) |" in text
    assert "The old mission (9 m, P_traj 20 %) is refused" in text
    assert f"P_traj {math.floor(100 * LIMIT.floor_reach_m(camp.ALTITUDE_M - camp.LEVER_ARM_Z_M) / 30)} %" in text
