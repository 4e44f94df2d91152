"""tools.pose_correction_campaign: what it flies and how it tabulates (the flights themselves run in the campaign)."""

from pathlib import Path

import trimesh

from tools.pose_correction_campaign import Building, own_pile, table


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
    assert vio.endswith("| 2/2 | 1/2 |")  # 0.3 vs 0.1 and 0.6 vs 0.5: both within 0.3 pp; one RMS <= 10 cm
