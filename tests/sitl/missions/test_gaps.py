"""Gap re-flights (`plan --fill-gaps REPORT_DIR`): what a report could not see, a short mission over it."""

import json
import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from firmware_py.core.sensor import LIDARLITE_V3
from firmware_py.core.site import DEFAULT_SITE, Site
from firmware_py.core.storage import Storage
from firmware_py.core.waveform import named_waveform
from ground.render import write_ply
from ground.surface_file import SavedSurface, save_surface
from sitl.cli import main
from sitl.missions.coverage import CoverageTarget, LoopPlan, floor_hits_w
from sitl.missions.gaps import load_gaps, plan_fill_gaps
from sitl.missions.range_check import RangeLimit

SMALL = Storage(30.0, 20.0, 10.0)
WF = named_waveform("semi-triangular", 5.0, 0)
LIDAR = RangeLimit(LIDARLITE_V3.max_range_m)
CELL = 0.5


def _report(tmp_path, fitted: np.ndarray | None, heights: np.ndarray | None = None, site: dict | None = None,
            storage: Storage = SMALL, cloud_xy: np.ndarray | None = None):
    """A finished report directory as `pilescan-ground report` writes it: report.json, surface.npz (by the
    ground's own writer; fitted None: a version 1 file) and, optionally, cloud.ply."""
    d = tmp_path / "report"
    d.mkdir(exist_ok=True)
    h = np.zeros((60, 40)) if heights is None else heights
    save_surface(SavedSurface(h, storage.length_m, storage.width_m, storage.height_m, CELL, 0.0, 0.0, 0.0, 0.0,
                              site=site, fitted=fitted), d / "surface.npz")
    (d / "report.json").write_text(json.dumps({"coverage_ratio_pct": 90.0}))
    if cloud_xy is not None:
        write_ply(np.column_stack([cloud_xy, np.zeros(len(cloud_xy))]), d / "cloud.ply")
    return d


def _corner_gap() -> np.ndarray:
    """Seen everywhere but a 5 x 4 m block in the south-west corner."""
    fitted = np.ones((60, 40), dtype=bool)
    fitted[:10, :8] = False
    return fitted


def _target(pct: float = 95.0) -> CoverageTarget:
    return CoverageTarget(pct, WF, LIDAR, LIDARLITE_V3.rate_hz)


def test_that_a_plan_over_a_known_gap_covers_it_with_a_short_flight(tmp_path):
    gaps = load_gaps(_report(tmp_path, _corner_gap()), SMALL)
    assert int(gaps.unseen.sum()) == 80 and len(gaps.regions) >= 1
    planned = plan_fill_gaps(SMALL, gaps, _target(), altitude_m=8.0)
    assert planned.coverage.gap_pct >= 95.0
    # independently of the hull: nearly every gap cell has a floor hit of the planned flight within the seen radius
    hits = floor_hits_w(planned.mission, WF, LIDAR, LIDARLITE_V3.rate_hz)
    ix, iy = np.nonzero(gaps.unseen)
    d, _ = cKDTree(hits).query(np.column_stack([(ix + 0.5) * CELL, (iy + 0.5) * CELL]))
    assert (d <= 1.0).mean() >= 0.95
    loop = LoopPlan((1.0, 1.5, 1.0, 1.5)).mission(SMALL, 8.0, math.radians(30))  # the loop nearest the walls
    assert planned.mission.path_length_m() < 0.5 * loop.path_length_m()
    assert planned.mission.plan["kind"] == "fill-gaps" and planned.mission.plan["gap_cells"] == 80


def test_that_a_band_along_several_walls_is_one_region_per_wall(tmp_path):
    fitted = np.zeros((60, 40), dtype=bool)
    fitted[6:-6, 6:-6] = True  # a 3 m band of unseen floor round the walls
    gaps = load_gaps(_report(tmp_path, fitted), SMALL)
    assert len(gaps.regions) == 4
    assert np.array_equal(np.logical_or.reduce(gaps.regions), gaps.unseen)
    planned = plan_fill_gaps(SMALL, gaps, _target(90.0), altitude_m=8.0)
    assert planned.coverage.gap_pct >= 90.0


def test_that_a_report_that_saw_everything_is_refused(tmp_path):
    with pytest.raises(ValueError, match="no gaps to re-fly"):
        load_gaps(_report(tmp_path, np.ones((60, 40), dtype=bool)), SMALL)


def test_that_a_missing_or_unfinished_report_is_refused(tmp_path):
    with pytest.raises(ValueError, match="no such report directory"):
        load_gaps(tmp_path / "nowhere", SMALL)
    d = _report(tmp_path, _corner_gap())
    (d / "report.json").unlink()  # a report that failed half-way has no report.json
    with pytest.raises(ValueError, match="holds no finished report"):
        load_gaps(d, SMALL)


def test_that_a_corrupt_surface_file_is_refused(tmp_path):
    d = _report(tmp_path, _corner_gap())
    (d / "surface.npz").write_bytes(b"PK\x03\x04 not a zip at all")
    with pytest.raises(ValueError, match="is not a pilescan surface file"):
        load_gaps(d, SMALL)


def test_that_a_report_of_another_building_or_site_is_refused(tmp_path):
    with pytest.raises(ValueError, match="not the 32x20x10 m one being planned"):
        load_gaps(_report(tmp_path, _corner_gap()), Storage(32.0, 20.0, 10.0))
    d = _report(tmp_path, _corner_gap(), site=DEFAULT_SITE.to_dict())
    assert load_gaps(d, SMALL, DEFAULT_SITE).unseen.any()
    turned = Site(DEFAULT_SITE.corner, math.radians(90.0))
    with pytest.raises(ValueError, match="another building: the buildings' x axes are 90 deg apart"):
        load_gaps(d, SMALL, turned)


def test_that_a_version_1_surface_takes_its_gaps_from_the_clouds_hull_or_is_refused_without_it(tmp_path):
    d = _report(tmp_path, None)  # no fitted mask, no cloud: what was seen is unknown
    with pytest.raises(ValueError, match="does not say which cells were seen"):
        load_gaps(d, SMALL)
    d = _report(tmp_path, None, cloud_xy=_dense(5.0, 30.0, 4.0, 20.0))
    gaps = load_gaps(d, SMALL)
    assert gaps.unseen[:10, :].all() and gaps.unseen[:, :8].all() and not gaps.unseen[20:, 20:].any()


def _dense(x0: float, x1: float, y0: float, y1: float, step: float = 0.5) -> np.ndarray:
    """Points every step over a rectangle, as a flight's fans cover the ground they see."""
    gx, gy = np.meshgrid(np.arange(x0, x1 + 1e-9, step), np.arange(y0, y1 + 1e-9, step), indexing="ij")
    return np.column_stack([gx.ravel(), gy.ravel()])


def test_that_the_cells_a_reports_hull_bridged_far_from_any_point_are_gaps_too(tmp_path, capsys):
    """Fitted everywhere but the corner block, and the points cover the floor but a 5 x 4 m hole in the middle (a
    trough a pile's shoulder hid, which the hull's triangles bridged): the hole is a gap as well, but for its rim
    within the seen radius (1 m: two cells) of the points around it, and counts in the merged R_a as the report's hull
    did."""
    pts = _dense(0.0, 30.0, 0.0, 20.0)
    hole = (pts[:, 0] > 12.5) & (pts[:, 0] < 17.5) & (pts[:, 1] > 8.0) & (pts[:, 1] < 12.0)
    corner = (pts[:, 0] < 5.0) & (pts[:, 1] < 4.0)
    gaps = load_gaps(_report(tmp_path, _corner_gap(), cloud_xy=pts[~hole & ~corner]), SMALL)
    assert gaps.bridged is not None and not (gaps.bridged & ~gaps.unseen).any()
    ix, iy = np.nonzero(gaps.bridged)
    # the points' cells: x = 12.5 and 17.5 m are cells 25 and 35, y = 8 and 12 m cells 16 and 24
    assert set(zip(ix.tolist(), iy.tolist(), strict=True)) == {(i, j) for i in range(28, 33) for j in range(19, 22)}
    assert int(gaps.unseen.sum()) == 80 + 15 and gaps.unseen[:10, :8].all()
    assert any((r & gaps.bridged).any() and not (r & ~gaps.bridged).any() for r in gaps.regions)  # the hole's own
    planned = plan_fill_gaps(SMALL, gaps, _target(), altitude_m=8.0)
    assert planned.coverage.gap_pct >= 95.0 and planned.coverage.covered[28:33, 19:22].all()
    # the hole was inside the report's R_a already: the merged R_a counts it whether or not the re-flight covers it
    assert planned.coverage.merged_ra_pct >= 100.0 * (1 - (80 - planned.coverage.covered[:10, :8].sum()) / 2400) - 1e-9
    assert main(["plan", "--fill-gaps", str(tmp_path / "report"), "--storage", "30x20x10", "--altitude", "8", "--out",
                 str(tmp_path / "gaps.waypoints")]) == 0
    assert "95 unseen cells (23.8 m², 15 of them inside the report's hull but with no point within 1 m)" in \
        capsys.readouterr().out
    # a damaged cloud is refused in one line (the plan would leave its bridges out unsaid); without a cloud the fitted
    # mask alone says what was seen, as before
    (tmp_path / "report" / "cloud.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\n")
    with pytest.raises(ValueError, match=r"cloud\.ply is not a readable point cloud"):
        load_gaps(tmp_path / "report", SMALL)
    (tmp_path / "report" / "cloud.ply").unlink()
    assert load_gaps(tmp_path / "report", SMALL).bridged is None


def test_that_plan_fill_gaps_writes_a_plan_and_says_what_it_covers(tmp_path, capsys):
    d = _report(tmp_path, _corner_gap())
    out = tmp_path / "gaps.waypoints"
    assert main(["plan", "--fill-gaps", str(d), "--storage", "30x20x10", "--altitude", "8", "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert "80 unseen cells (20.0 m²)" in said and "predicted to cover" in said and "kJ" in said
    assert out.read_text().startswith("QGC WPL 110")


@pytest.mark.parametrize("fitted, extra, message", [
    (np.ones((60, 40), dtype=bool), [], "no gaps to re-fly"),
    (_corner_gap(), ["--storage", "31x20x10"], "not the 31x20x10 m one being planned"),
    (_corner_gap(), ["--coverage", "99"], "--coverage, --surface, --all-phases and --bare-walls are not used with it"),
    (_corner_gap(), ["--gap-coverage", "100.5"], "target coverage must be in (0, 100] %"),
])
def test_that_plan_fill_gaps_refuses_in_one_line(tmp_path, capsys, fitted, extra, message):
    d = _report(tmp_path, fitted)
    argv = ["plan", "--fill-gaps", str(d), "--storage", "30x20x10", "--altitude", "8", *extra,
            "--out", str(tmp_path / "p.waypoints")]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err
    assert not (tmp_path / "p.waypoints").exists()


def test_that_fill_gaps_outside_its_mission_is_refused(tmp_path, capsys):
    argv = ["fly", "--stockpile", "1", "--p-traj", "20", "--fill-gaps", str(tmp_path), "--out", str(tmp_path / "r")]
    assert main(argv) == 2
    assert "add --mission fill-gaps" in capsys.readouterr().err
