"""pilescan-ground compare (ground.compare): known cut and fill on synthetic surfaces, the intervals' sides,
the files written, and the command's bad inputs as one line and exit 2."""

import json
import shutil

import numpy as np
import pytest

from firmware_py.core.cli import ExitCode, UserError
from ground.cli import main
from ground.compare import change_record, compare_surfaces, write_compare
from ground.surface import Grid, grid_volume
from ground.surface_file import SavedSurface, load_surface, save_surface

GRID = Grid(30.0, 20.0, 0.5)


def saved(heights: np.ndarray, grid: Grid = GRID, below: float = 20.0, above: float = 20.0,
          sigma: float = 0.02) -> SavedSurface:
    return SavedSurface(heights, grid.length_m, grid.width_m, 10.0, grid.cell_m, grid_volume(heights, grid),
                        below, above, sigma)


def cut_and_fill() -> tuple[SavedSurface, SavedSurface]:
    """A 2 m pile; 1 m taken off a 4 x 4 m patch (16 m³ cut) and 0.5 m added on a 6 x 2 m one (6 m³ fill)."""
    rng = np.random.default_rng(0)
    old = np.full(GRID.shape, 2.0) + rng.normal(0, 0.005, GRID.shape)
    new = old + rng.normal(0, 0.005, GRID.shape)
    cx, cy = GRID.centres()
    new[(cx > 4) & (cx < 8) & (cy > 4) & (cy < 8)] -= 1.0
    new[(cx > 20) & (cx < 26) & (cy > 10) & (cy < 12)] += 0.5
    return saved(old), saved(new)


def test_that_a_known_cut_and_fill_are_measured_with_their_net():
    old, new = cut_and_fill()
    c = compare_surfaces(old, new)
    assert c.cut_m3 == pytest.approx(16.0, rel=0.01)
    assert c.fill_m3 == pytest.approx(6.0, rel=0.01)
    assert c.net_m3 == pytest.approx(-10.0, abs=0.5)
    assert c.cut_area_m2 == pytest.approx(16.0) and c.fill_area_m2 == pytest.approx(12.0)
    for v, (lo, hi) in ((c.net_m3, c.net_interval_m3), (c.cut_m3, c.cut_interval_m3), (c.fill_m3, c.fill_interval_m3)):
        assert lo < v < hi


def test_that_noise_below_the_level_of_detection_is_neither_cut_nor_fill():
    old, _ = cut_and_fill()
    noisy = saved(old.heights_m + np.random.default_rng(5).normal(0, 0.02, GRID.shape))
    c = compare_surfaces(old, noisy)
    every_cell_m3 = float(np.abs(c.diff_m).sum() * GRID.cell_area_m2)  # what summing |change| would call cut + fill
    assert c.cut_m3 + c.fill_m3 < 0.1 * every_cell_m3
    lo, hi = c.net_interval_m3
    assert lo < c.net_m3 < hi and lo < 0 < hi


def test_that_an_offset_between_the_flights_widens_the_net_interval():
    old, _ = cut_and_fill()
    shifted = saved(old.heights_m + 0.01)  # a 1 cm height bias of the new flight, under the detection level
    same = compare_surfaces(old, saved(old.heights_m.copy()))
    c = compare_surfaces(old, shifted)
    assert c.net_m3 == pytest.approx(6.0, rel=0.01)
    assert c.net_interval_m3[1] - c.net_interval_m3[0] > (same.net_interval_m3[1] - same.net_interval_m3[0]) + 10


def test_that_the_net_interval_pairs_new_below_with_old_above():
    base = np.full(GRID.shape, 1.0)
    new = base.copy()
    new[:10, :10] += 1.0  # 25 m² changed
    c = compare_surfaces(saved(base, below=0.0, above=50.0), saved(new, below=0.0, above=0.0))
    assert c.net_m3 - c.net_interval_m3[0] > 5 * (c.net_interval_m3[1] - c.net_m3)


def test_that_surveys_of_different_buildings_are_not_compared():
    with pytest.raises(UserError, match="buildings differ"):
        compare_surfaces(saved(np.ones(GRID.shape)), saved(np.ones((62, 40)), Grid(31.0, 20.0, 0.5)))


def test_that_the_compare_files_are_written_and_read_back(tmp_path):
    old, new = cut_and_fill()
    c = compare_surfaces(old, new)
    rec = change_record(c, old, new, "a", "b", None, -10.0)
    write_compare(c, rec, tmp_path / "cmp")
    got = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    assert got["cut_m3"] == pytest.approx(c.cut_m3) and got["per_pile"] is None and got["truth_in_interval"]
    with np.load(tmp_path / "cmp" / "cutfill.npz") as z:
        assert np.array_equal(z["diff_m"], c.diff_m, equal_nan=True) and len(z["x_edges_m"]) == GRID.shape[0] + 1
    assert (tmp_path / "cmp" / "cutfill.png").read_bytes()[:4] == b"\x89PNG"


def reports(tmp_path):
    old, new = cut_and_fill()
    for name, s in (("old", old), ("new", new)):
        (tmp_path / name).mkdir()
        save_surface(s, tmp_path / name / "surface.npz")
        (tmp_path / name / "report.json").write_text("{}")
    return tmp_path / "old", tmp_path / "new"


def test_that_compare_prints_net_cut_and_fill_of_two_report_directories(tmp_path, capsys):
    old, new = reports(tmp_path)
    assert main(["compare", str(old), str(new), "--out", str(tmp_path / "cmp"), "--true-change", "-10"]) == 0
    out = capsys.readouterr().out
    assert "net change" in out and "cut" in out and "fill" in out and "inside the interval" in out
    assert load_surface(new / "surface.npz").volume_m3 > 0


@pytest.mark.parametrize("make, match", [
    (lambda t: t / "missing", "no such run or report directory"),
    (lambda t: (t / "empty").mkdir() or t / "empty", "neither a run directory"),
    (lambda t: (t / "f.txt").write_text("x") and t / "f.txt", "is not a run or report directory"),
    (lambda t: ((t / "rep").mkdir(), (t / "rep" / "report.json").write_text("{}")) and t / "rep",
     "without its surface.npz"),
])
def test_that_compare_refuses_what_is_not_a_run_or_report_in_one_line_with_exit_2(tmp_path, capsys, make, match):
    old, _ = reports(tmp_path)
    bad = make(tmp_path)
    for argv in (["compare", str(old), str(bad)], ["compare", str(bad), str(old)]):
        code = main([*argv, "--out", str(tmp_path / "cmp")])
        err = capsys.readouterr().err
        assert code == ExitCode.USAGE, err
        assert err.count("\n") == 1 and "Traceback" not in err and match in err
        assert not (tmp_path / "cmp").exists()


def test_that_one_survey_given_twice_is_refused_not_a_change_of_0_with_no_uncertainty(tmp_path, capsys):
    old, _ = reports(tmp_path)
    copy = tmp_path / "copy"
    shutil.copytree(old, copy)
    assert main(["compare", str(old), str(copy), "--out", str(tmp_path / "cmp")]) == ExitCode.USAGE
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "hold the same surface" in err and not (tmp_path / "cmp").exists()


def test_that_a_damaged_surface_file_in_compare_is_one_line(tmp_path, capsys):
    old, new = reports(tmp_path)
    (new / "surface.npz").write_bytes(b"PK\x03\x04 damaged")
    assert main(["compare", str(old), str(new), "--out", str(tmp_path / "cmp")]) == ExitCode.USAGE
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not a pilescan surface file" in err


def test_that_report_refuses_a_base_that_is_not_a_run_or_report_in_one_line(tmp_path, capsys):
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "samples.pslog").write_bytes(b"")
    code = main(["report", str(tmp_path / "run"), "--out", str(tmp_path / "r"), "--base", str(tmp_path / "nope")])
    err = capsys.readouterr().err
    assert code == ExitCode.USAGE and err.count("\n") == 1 and "no such run or report directory" in err
