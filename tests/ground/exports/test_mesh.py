"""The mesh export, read back by trimesh: a closed solid whose volume is the report's grid volume."""

import numpy as np
import pytest
import trimesh
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from ground.exports.mesh import VOLUME_RTOL, surface_solid, write_mesh
from ground.surface import Grid, grid_volume
from tests.fuzz_budget import budget
from tests.ground.exports.conftest import STORAGE


def test_that_the_surface_solid_holds_the_reports_volume(flown):
    mesh = trimesh.load(flown.report_dir / "surface.ply", process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume == pytest.approx(flown.report["volume_m3"], rel=VOLUME_RTOL)
    h = flown.survey.heights
    nx, ny = flown.survey.grid.shape
    assert np.isfinite(h).all()  # the default empty-cell policy defines every cell, so:
    assert len(mesh.vertices) == 2 * (nx + 1) * (ny + 1) + nx * ny  # corners top and bottom, one per centre
    assert len(mesh.faces) == 6 * nx * ny + 4 * (nx + ny)  # 4 + 2 per cell, 2 per outer edge
    assert mesh.bounds[0] == pytest.approx([0.0, 0.0, min(0.0, h.min())])
    assert mesh.bounds[1] == pytest.approx([STORAGE.length_m, STORAGE.width_m, h.max()])


def test_that_holes_islands_and_negative_cells_keep_the_volume_exact_and_the_solid_closed(tmp_path):
    grid = Grid(8.0, 5.0, 0.5)
    rng = np.random.default_rng(3)
    h = rng.uniform(-0.05, 3.0, grid.shape)
    h[rng.random(grid.shape) < 0.3] = np.nan  # holes and islands, cells touching only at a corner
    mesh = trimesh.load(write_mesh(h, grid, tmp_path / "m.ply"), process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume == pytest.approx(grid_volume(h, grid), rel=VOLUME_RTOL)
    assert mesh.vertices.dtype == np.float64


def test_that_a_single_cell_is_a_four_sided_box_with_a_pyramid_roof():
    grid = Grid(2.0, 2.0, 1.0)
    h = np.array([[2.0, np.nan], [np.nan, np.nan]])
    vertices, faces = surface_solid(h, grid)
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    assert len(vertices) == 9 and len(faces) == 4 + 2 + 8
    assert mesh.volume == pytest.approx(2.0)  # corners at 2 (the only cell's mean), centre at 2: a box


def test_that_no_defined_cell_is_no_solid(tmp_path):
    grid = Grid(2.0, 2.0, 1.0)
    v, f = surface_solid(np.full(grid.shape, np.nan), grid)
    assert v.shape == (0, 3) and f.shape == (0, 3)
    with pytest.raises(ValueError, match="no cell"):
        write_mesh(np.full(grid.shape, np.nan), grid, tmp_path / "m.ply")


@budget(60, deadline=None)
@given(arrays(np.float64, (5, 4), elements=st.one_of(st.just(np.nan), st.floats(-0.5, 20.0))))
def test_that_any_pattern_of_defined_cells_gives_a_closed_solid_of_the_grid_volume(h):
    grid = Grid(2.5, 2.0, 0.5)
    vertices, faces = surface_solid(h, grid)
    if not np.isfinite(h).any():
        assert len(faces) == 0
        return
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    with np.errstate(invalid="ignore", divide="ignore"):  # trimesh's centre of mass of a zero-volume solid
        volume = mesh.volume
    assert volume == pytest.approx(grid_volume(h, grid), rel=VOLUME_RTOL, abs=1e-9)


def test_that_a_mesh_too_big_for_the_memory_allowed_is_refused_before_the_survey(flown, tmp_path):
    from firmware_py.core.cli import UserError
    from ground.exports.formats import ExportFormat
    from ground.report import ReportOptions, make_report

    opts = ReportOptions(plots=False, cell_m=0.05, max_grid_memory_bytes=50 * 2**20, exports=(ExportFormat.MESH,))
    with pytest.raises(UserError, match=r"--export mesh of 240,000 cells would need about 160 MiB") as exc:
        make_report(flown.run, tmp_path / "rep", opts)
    assert "\n" not in str(exc.value) and not (tmp_path / "rep" / "report.json").exists()
    # without the mesh the same grid fits: the refusal is the mesh's
    make_report(flown.run, tmp_path / "rep", ReportOptions(plots=False, cell_m=0.05, max_grid_memory_bytes=50 * 2**20))
