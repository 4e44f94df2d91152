"""The ground's reader of a saved surface (ground.surface_file.load_surface): every metadata number it uses is
checked by the shared `firmware_py.core.surface_file.meta_number`, with the same bounds on the building and the
cell as the coverage planner's reader (tests/sitl/missions/test_surveyed_surface.py), and refused as one line."""


import numpy as np
import pytest

from firmware_py.core.cli import ExitCode, UserError
from ground.cli import main
from ground.surface import Grid
from ground.surface_file import SavedSurface, load_surface, save_surface
from tests.firmware_py.core.test_surface_file import BUILDING_OR_CELL_CASES, edit_meta

GRID = Grid(30.0, 20.0, 0.5)


def _saved(path):
    return save_surface(SavedSurface(np.ones(GRID.shape), 30.0, 20.0, 10.0, 0.5, 600.0, 5.0, 7.0, 0.02), path)


@pytest.mark.parametrize("key, value, message", [
    # the building and the cell: the same bounds as the planner's reader (a sub-centimetre cell was the grid's
    # "cell size" error here)
    *BUILDING_OR_CELL_CASES,
    # the volume, its interval and the scatter: bounded by the building
    ("volume_m3", float("inf"), r"volume_m3 must be a finite number within -300 to 6300, got inf"),
    ("below_m3", None, r"below_m3 must be a finite number within 0 to 6300, got None"),
    ("above_m3", -1.0, r"above_m3 must be a finite number within 0 to 6300, got -1\.0"),
    ("scatter_sigma_m", "0.02", r"scatter_sigma_m must be a finite number within 0 to 10, got '0\.02'"),
    ("scatter_sigma_m", 11.0, r"scatter_sigma_m must be a finite number within 0 to 10, got 11\.0"),
])
def test_that_a_surface_file_whose_numbers_are_not_usable_is_one_clear_error(tmp_path, key, value, message):
    p = edit_meta(_saved(tmp_path / "surface.npz"), key, value)
    with pytest.raises(UserError, match=message) as e:
        load_surface(p)
    assert "\n" not in str(e.value) and str(e.value).startswith(f"{p}: surface file field {key} ")


def test_that_a_surface_file_with_its_numbers_within_bounds_reads(tmp_path):
    s = load_surface(_saved(tmp_path / "surface.npz"))
    assert (s.length_m, s.width_m, s.height_m, s.cell_m, s.volume_m3, s.below_m3, s.above_m3, s.scatter_sigma_m) \
        == (30.0, 20.0, 10.0, 0.5, 600.0, 5.0, 7.0, 0.02)


def test_that_compare_refuses_a_surface_file_whose_building_is_no_number_with_one_line(tmp_path, capsys):
    for name in ("old", "new"):
        (tmp_path / name).mkdir()
        _saved(tmp_path / name / "surface.npz")
        (tmp_path / name / "report.json").write_text("{}")
    edit_meta(tmp_path / "new" / "surface.npz", "length_m", float("nan"))
    code = main(["compare", str(tmp_path / "old"), str(tmp_path / "new"), "--out", str(tmp_path / "cmp")])
    err = capsys.readouterr().err
    assert code == ExitCode.USAGE, err
    assert err.count("\n") == 1 and "Traceback" not in err and "length_m must be a finite number >= 0.001" in err
    assert not (tmp_path / "cmp").exists()
