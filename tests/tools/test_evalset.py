"""tools.evalset: the grid, its split, its stored runs and its rows (one quick run; the set itself is data)."""

import json

import numpy as np
import pytest

from sitl.world.shapes import Family
from tools.evalset import (
    BUILDINGS,
    HELDOUT_BUILDINGS,
    HELDOUT_FAMILIES,
    NOISES,
    PILE_CLEARANCE_M,
    Split,
    cases_for,
    fill_table,
    instance_of,
    instances,
    iter_runs,
    load_run,
    main,
    mission_for,
    phases_of,
    split_of,
    summary_table,
    survey_of,
)
from tools.sweep import read_rows_csv


def test_that_the_split_is_deterministic_disjoint_and_by_whole_pile():
    a, b = instances(), instances()
    assert a == b
    cal = {(i.building, i.family, i.seed) for i in a if i.split is Split.CALIBRATION}
    held = {(i.building, i.family, i.seed) for i in a if i.split is Split.HELDOUT}
    assert cal and held and not cal & held
    assert len({(i.family, i.seed) for i in a}) == len(a)  # no two piles share a family and seed
    for i in a:
        if i.building in HELDOUT_BUILDINGS or i.family in HELDOUT_FAMILIES:
            assert i.split is Split.HELDOUT
    # every case (P_traj) of one pile is on the same side: the split is a function of the pile alone
    for c in cases_for(a):
        inst = instance_of(c)
        assert split_of(inst.building, inst.family, inst.seed) is inst.split


def test_that_calibration_holds_every_family_but_the_held_out_ones_and_both_sides_hold_several_buildings():
    ins = instances()
    cal_families = {i.family for i in ins if i.split is Split.CALIBRATION}
    assert cal_families == set(Family) - HELDOUT_FAMILIES
    assert len({i.building for i in ins if i.split is Split.HELDOUT}) >= 2


def test_that_the_set_has_more_than_a_thousand_runs_over_three_buildings_and_several_altitudes():
    cases = cases_for(instances())
    n_runs = sum(c.get("phases") * len(c.get("noises").split(",")) for c in cases)
    assert n_runs >= 1000
    assert len(BUILDINGS) >= 3
    assert len({(i.building, i.altitude_m) for i in instances()}) >= 2 * len(BUILDINGS)


def test_that_every_pile_fits_under_its_flight_and_every_mission_is_flyable():
    for inst in instances():
        shape = inst.shape()
        assert shape.pile.max_height_m <= inst.altitude_m - PILE_CLEARANCE_M + 1e-9
        for p in (5, 35):
            mission_for(inst.building, inst.altitude_m, p)  # raises when it does not fit


def test_that_servo_phases_are_distinct_deterministic_and_vary_between_cases():
    cases = cases_for(instances())
    phases = [phases_of(c) for c in cases]
    assert phases == [phases_of(c) for c in cases]
    assert all(len(set(p)) == len(p) == 3 and all(0 <= k < 20 for k in p) for p in phases)
    assert len({tuple(p) for p in phases}) > 10


def test_that_a_quick_run_stores_runs_and_rows_the_ground_station_reproduces(tmp_path):
    root = tmp_path / "evalset"
    doc = tmp_path / "evaluation_set.md"
    assert main(["--quick", "--noises", "none", "--root", str(root), "--flight-cache", str(tmp_path / "flights"),
                 "--no-progress", "--write", str(doc)]) == 0
    rows = read_rows_csv(root / "rows.csv")
    assert len(rows) == 2
    for r in rows:
        for key in ("volume_m3", "true_volume_m3", "error_m3", "ra_pct", "filled_cell_frac", "filled_volume_m3",
                    "n_points", "p_traj_pct", "phase", "noise", "building", "family", "split", "altitude_m"):
            assert r[key] is not None, key
        assert r["n_points"] > 1000 and 0 <= r["filled_cell_frac"] <= 1
    empty = next(r for r in rows if r["family"] == "empty")
    assert empty["true_volume_m3"] == 0 and empty["ve_pct"] is None
    pile = next(r for r in rows if r["family"] != "empty")
    assert pile["ve_pct"] == pytest.approx(100 * pile["error_m3"] / pile["true_volume_m3"])
    runs = list(iter_runs(root=root))
    assert sorted(r.run_id for r in runs) == sorted(r["run_id"] for r in rows)
    by_split = {s: [r.run_id for r in iter_runs(s, root=root)] for s in Split}
    assert sorted(by_split[Split.CALIBRATION] + by_split[Split.HELDOUT]) == sorted(r.run_id for r in runs)
    for run in runs:  # the stored samples give the row's volume again, without re-sampling
        row = next(r for r in rows if r["run_id"] == run.run_id)
        from ground.surface import grid_volume
        sv = survey_of(run)
        assert grid_volume(sv.heights, sv.grid) == pytest.approx(row["volume_m3"], rel=1e-9)
        assert run.true_volume_m3 == row["true_volume_m3"] and run.split.value == row["split"]
    text = doc.read_text()
    assert "| corner | 35 % | 1 |" in text and "| empty | 35 % | 1 |" in text
    # --cached-only computes nothing and gives the same rows
    assert main(["--quick", "--noises", "none,datasheet", "--root", str(root), "--no-progress", "--cached-only",
                 "--flight-cache", str(tmp_path / "no-flights")]) == 0
    assert read_rows_csv(root / "rows.csv") == []  # the datasheet cases are not cached: no case has all its runs
    assert not (tmp_path / "no-flights").exists()
    assert main(["--quick", "--noises", "none", "--root", str(root), "--no-progress", "--cached-only"]) == 0
    assert read_rows_csv(root / "rows.csv") == rows


def test_that_an_incomplete_run_is_named(tmp_path):
    run = tmp_path / "runs" / "x"
    run.mkdir(parents=True)
    (run / "truth.json").write_text(json.dumps({"run_id": "x", "split": "heldout"}))
    with pytest.raises(ValueError, match="incomplete or unreadable"):
        load_run(run)
    np.save(run / "samples.npy", np.zeros(3))
    (run / "header.json").write_text("{not json")
    with pytest.raises(ValueError, match=str(run)):
        load_run(run)


def test_that_bad_noise_option_is_one_line_and_exit_2(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--quick", "--noises", "gaussian"])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "--noises must be" in err and "Traceback" not in err


def test_that_the_summary_gives_median_and_max_per_family_p_traj_and_noise():
    rows = [{"family": "cone", "p_traj_pct": 20, "noise": "none", "ve_abs_pct": v, "error_m3": v}
            for v in (1.0, 2.0, 4.0)]
    rows.append({"family": "empty", "p_traj_pct": 20, "noise": "none", "ve_abs_pct": None, "error_m3": -3.0})
    text = summary_table(rows)
    assert "| cone | 20 % | 3 | 2.00 / 4.00 |" in text
    assert "| empty | 20 % | 1 | \\|error\\| 3.0 / 3.0 m³ |" in text
    assert NOISES[0].value in text


def test_that_the_fill_table_counts_the_runs_whose_error_the_filled_volume_bounds():
    rows = [{"family": "corner", "ra_pct": ra, "filled_cell_frac": f, "filled_volume_m3": fv, "error_m3": e}
            for ra, f, fv, e in ((99.0, 0.01, 3.0, -2.0), (97.0, 0.03, 1.0, 5.0), (95.0, 0.05, -4.0, 4.0))]
    assert "| corner | 3 | 97.0 | 3.0 | 1.0 | 4.0 | 2 of 3 |" in fill_table(rows)


def test_that_a_case_at_the_lowest_p_traj_in_the_smallest_building_runs(tmp_path):
    from tools.evalset import run_case
    inst = next(i for i in instances() if i.building == "small")
    (case,) = cases_for([inst], p_traj_pct=(5,), phases=1, noises=(NOISES[0],))
    rows = run_case(case, root=tmp_path / "evalset", flight_cache=tmp_path / "flights")
    assert len(rows) == 1 and rows[0]["true_volume_m3"] > 0 and rows[0]["n_points"] > 1000
