"""The local-linear surface estimator (ground.smoothing behind ground.surface's ``local-linear``)."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from firmware_py.core.cli import UserError
from firmware_py.core.samplelog import read_samplelog
from firmware_py.core.sensor_noise import stated_angle_sigma_rad
from ground.report import header_geometry
from ground.smoothing import (
    DEFAULT_SMOOTHING,
    DEFAULT_Z_CRIT,
    SmoothingOptions,
    binned_moments,
    box_sum,
    cell_index,
    data_noise_scale,
    integral_image,
    lepski_select,
    smoothed_nodes,
    vertical_sigma_m,
    window_halfwidths,
)
from ground.surface import Grid, fit_heights, fit_heights_with_se, grid_volume

G = Grid(20, 10, 0.25)
GOLDEN = Path(__file__).resolve().parents[1] / "golden" / "samples.pslog"
RES_SIGMA = 0.01 / math.sqrt(12)  # a 1 cm range quantum: the smallest error any point has


def plane(xy):
    return 1.0 + 0.2 * xy[:, 0] + 0.1 * xy[:, 1]


def cone(xy):
    return np.maximum(0.0, 4.0 - 0.5 * np.hypot(xy[:, 0] - 10, xy[:, 1] - 5))


def swaths(rng, n_lines=6, per_line=3000, width_m=1.0):
    """Points along fan lines across the floor (as a swept beam leaves them), with the floor's corners."""
    ys = np.linspace(0.5, 9.5, n_lines)
    half = width_m / 2
    xy = np.vstack([np.column_stack([rng.uniform(0, 20, per_line), y + rng.uniform(-half, half, per_line)])
                    for y in ys])
    return np.vstack([xy, [[0, 0], [20, 0], [0, 10], [20, 10]]])


def cell_truth(fn):
    cx, cy = G.centres()
    return fn(np.column_stack([cx.ravel(), cy.ravel()])).reshape(cx.shape)


def test_that_on_a_dense_noisy_plane_the_estimate_is_closer_to_the_truth_than_the_interpolant():
    rng = np.random.default_rng(1)
    xy = swaths(rng, n_lines=20, per_line=4000)
    sigma = np.full(len(xy), 0.2)
    pts = np.column_stack([xy, plane(xy) + rng.normal(0, 0.2, len(xy))])
    truth = cell_truth(plane)
    rms = {m: np.sqrt(np.nanmean((fit_heights(pts, G, m, sigma) - truth) ** 2))
           for m in ("cubic-limited", "local-linear")}
    assert rms["local-linear"] < 0.5 * rms["cubic-limited"]


def test_that_points_far_outside_their_noise_do_not_lift_the_volume():
    rng = np.random.default_rng(2)
    xy = swaths(rng)
    sigma = np.full(len(xy), 0.1)
    z = plane(xy) + rng.normal(0, 0.1, len(xy))
    lifted = z.copy()
    bad = rng.choice(len(xy) - 4, 60, replace=False)  # wall returns that escaped: metres above the surface
    lifted[bad] += rng.uniform(2, 8, len(bad))

    def lift_m3(method):
        return (grid_volume(fit_heights(np.column_stack([xy, lifted]), G, method, sigma), G)
                - grid_volume(fit_heights(np.column_stack([xy, z]), G, method, sigma), G))

    assert lift_m3("cubic-limited") > 3.0  # 60 points of 18,000 lift the interpolant by metres^3
    assert abs(lift_m3("local-linear")) < 0.01 * lift_m3("cubic-limited")


def test_that_exact_sparse_points_are_honoured():
    rng = np.random.default_rng(3)
    xy = np.vstack([rng.uniform(0, 20, (150, 2)) * [1, 0.5], [[0, 0], [20, 0], [0, 10], [20, 10]]])
    pts = np.column_stack([xy, cone(xy)])
    nodes = smoothed_nodes(pts, np.full(len(pts), RES_SIGMA), G.shape, (0.25, 0.25))
    # a cell holding one exact point: the node is that point, within the error the point is stated to have
    counts = G.counts(xy)
    single = counts.ravel()[cell_index(pts, G.shape, (0.25, 0.25))] == 1
    lone = pts[single]
    found = {tuple(np.round(p[:2], 9)): p[2] for p in nodes.xyz}
    for p in lone:
        assert found[tuple(np.round(p[:2], 9))] == pytest.approx(p[2], abs=DEFAULT_Z_CRIT * RES_SIGMA)
    # and the surface is as close to the cone as the interpolant through the points
    truth = cell_truth(cone)
    h_ll = fit_heights(pts, G, "local-linear", np.full(len(pts), RES_SIGMA))
    h_cl = fit_heights(pts, G, "cubic-limited")
    assert np.nanmax(np.abs(h_ll - truth)) == pytest.approx(np.nanmax(np.abs(h_cl - truth)), rel=0.05)


def test_that_the_smoothing_grows_with_the_stated_noise_and_vanishes_without_it():
    rng = np.random.default_rng(4)
    xy = swaths(rng)
    pts = np.column_stack([xy, cone(xy) + rng.normal(0, 0.05, len(xy))])

    def mean_window(sigma, opts=DEFAULT_SMOOTHING):
        return smoothed_nodes(pts, np.full(len(pts), sigma), G.shape, (0.25, 0.25), opts).level.mean()

    tiny, stated, larger = mean_window(1e-6), mean_window(0.05), mean_window(0.5)
    assert tiny == 0.0  # exact points: each cell's own data, no window
    assert 0 < stated == larger  # a sigma stated above the data's scatter is held to what the data show ...
    believed = SmoothingOptions(noise_from_data=False)
    assert stated < mean_window(0.5, believed)  # ... and taken at its word without that check


def _moments(pts, sigma):
    flat = cell_index(pts, G.shape, (0.25, 0.25))
    return binned_moments(pts, np.full(len(pts), sigma), flat, G.shape, (10.0, 5.0))


def test_that_the_noise_scale_is_what_the_data_show_below_the_header_and_never_above_it():
    rng = np.random.default_rng(6)
    xy = swaths(rng, n_lines=10)
    noisy = np.column_stack([xy, plane(xy) + rng.normal(0, 0.05, len(xy))])
    assert data_noise_scale(_moments(noisy, 0.5)) == pytest.approx(0.1, rel=0.1)  # stated 10x the scatter
    assert data_noise_scale(_moments(noisy, 0.05)) == pytest.approx(1.0, abs=0.1)  # stated right
    assert data_noise_scale(_moments(noisy, 0.005)) == 1.0  # stated too small: the header's sigma is kept
    assert data_noise_scale(_moments(noisy[:5], 0.5)) == 1.0  # too few points to tell


def test_that_exact_points_of_a_dome_are_not_flattened_by_noise_the_header_states_but_they_lack():
    """A noise-free survey whose header states the sensor's datasheet noise: windows accepted against that
    noise would flatten a convex pile by one sign everywhere (1/2 tr(H Sigma_w)); scaled to the data's own
    scatter, the narrow windows win and the volume stays the interpolant's."""
    rng = np.random.default_rng(7)
    xy = swaths(rng, n_lines=12, per_line=4000)
    pts = np.column_stack([xy, cone(xy)])
    truth_m3 = grid_volume(cell_truth(cone), G)
    sigma = np.full(len(pts), 0.05)

    def err_m3(opts):
        return grid_volume(fit_heights(pts, G, "local-linear", sigma, opts), G) - truth_m3

    stated, from_data = err_m3(SmoothingOptions(noise_from_data=False)), err_m3(SmoothingOptions())
    assert stated < 0 and abs(from_data) < 0.25 * abs(stated)


def test_that_the_chosen_windows_refitted_as_quadratics_do_not_flatten_a_noisy_cone():
    """Noisy points of a cone (5 cm, as the header states): the windows Lepski's rule accepts are wide, and their
    planes flatten the cone by one sign everywhere; the same windows refitted as quadratics hold its bend."""
    rng = np.random.default_rng(7)
    xy = swaths(rng, n_lines=12, per_line=4000)
    pts = np.column_stack([xy, cone(xy) + rng.normal(0.0, 0.05, len(xy))])
    truth_m3 = grid_volume(cell_truth(cone), G)
    sigma = np.full(len(pts), 0.05)

    def err_m3(opts):
        return grid_volume(fit_heights(pts, G, "local-linear", sigma, opts), G) - truth_m3

    plane, quadratic = err_m3(SmoothingOptions()), err_m3(SmoothingOptions(quadratic=True))
    assert plane < 0 and abs(quadratic) < 0.1 * abs(plane)


def test_that_a_cells_points_centroid_lies_on_a_plane_so_binning_alone_adds_no_bias():
    rng = np.random.default_rng(5)
    xy = swaths(rng)
    pts = np.column_stack([xy, plane(xy)])
    h = fit_heights(pts, G, "local-linear", np.full(len(pts), RES_SIGMA))
    assert np.nanmax(np.abs(h - cell_truth(plane))) < 1e-6  # Clough-Tocher's gradients are iterated to 1e-6


def test_that_the_standard_error_falls_as_one_over_root_n_and_is_nan_for_interpolants():
    rng = np.random.default_rng(6)
    se = []
    for n in (16_000, 64_000):  # 5 and 20 points a cell
        xy = rng.uniform(0, 1, (n, 2)) * [20, 10]
        pts = np.column_stack([xy, plane(xy) + rng.normal(0, 0.1, n)])
        h, s = fit_heights_with_se(pts, G, "local-linear", np.full(n, 0.1), SmoothingOptions(max_window_m=0))
        assert np.isfinite(s[np.isfinite(h)]).all() and np.isnan(s[~np.isfinite(h)]).all()
        se.append(np.nanmedian(s))
    assert se[1] == pytest.approx(se[0] / 2, rel=0.25)
    h, s = fit_heights_with_se(pts, G, "cubic-limited", np.full(len(pts), 0.1))
    assert np.isnan(s).all() and np.isfinite(h).any()
    h, s = fit_heights_with_se(pts, G, "local-linear")  # no sigmas: exact points, no variance to state
    assert np.isnan(s).all() and np.isfinite(h).any()


def test_that_bad_sigmas_are_refused():
    pts = np.array([[1, 1, 0.0], [5, 1, 0.0], [1, 5, 0.0], [5, 5, 1.0]])
    for sigma in (np.ones(3), np.array([1, 1, 0, 1.0]), np.array([1, 1, np.nan, 1.0])):
        with pytest.raises(ValueError, match="sigma"):
            fit_heights(pts, G, "local-linear", sigma)
    for bad in ({"z_crit": 0.0}, {"max_window_m": -1.0}, {"outlier_n_sigma": 0.0}):
        with pytest.raises(ValueError, match="smoothing"):
            SmoothingOptions(**bad)


def test_that_the_vertical_sigma_combines_range_angle_position_and_quantum():
    down, level = np.array([[0, 0, -1.0]]), np.array([[1.0, 0, 0]])
    r = np.array([10.0])
    s = vertical_sigma_m(0.025, 0.01, 0.113, math.radians(1), r, down)
    assert s[0] == pytest.approx(math.sqrt(0.025**2 + 0.113**2 + 0.01**2 / 12))  # no angle term straight down
    s = vertical_sigma_m(0.025, 0.01, 0.0, math.radians(1), r, level)
    assert s[0] == pytest.approx(math.sqrt((10 * math.radians(1)) ** 2 + 0.01**2 / 12))  # no range term level
    assert vertical_sigma_m(0.0, 0.0, 0.0, 0.0, r, down)[0] == 0.0


def test_that_the_angle_sigma_is_read_from_the_noise_record_and_bad_values_are_refused():
    assert stated_angle_sigma_rad({}) == 0.0
    rec = {"sensor_noise": {"model": "appendix-a", "servo_sigma_rad": 0.03, "attitude_sigma_rad": 0.04}}
    assert stated_angle_sigma_rad(rec) == pytest.approx(0.05)
    for bad in (-1, "x", True, float("nan")):
        with pytest.raises(ValueError, match="servo_sigma_rad"):
            stated_angle_sigma_rad({"sensor_noise": {"servo_sigma_rad": bad}})
    with pytest.raises(ValueError, match="JSON object"):
        stated_angle_sigma_rad({"sensor_noise": [1]})


def test_that_a_log_whose_noise_record_is_malformed_is_refused_with_one_line():
    log = read_samplelog(GOLDEN)
    log.header["sensor_noise"] = {"model": "appendix-a", "servo_sigma_rad": -1}
    with pytest.raises(UserError, match="servo_sigma_rad"):
        header_geometry(log, GOLDEN)


def test_that_lepski_takes_the_widest_window_that_agrees_with_every_narrower_one():
    est = np.array([[0.0, 0.0, 0.0], [0.1, 0.1, 0.5], [0.15, 0.9, 0.5]])  # rows: narrow -> wide
    se = np.array([[0.1, 0.1, 0.1], [0.05, 0.05, 0.05], [0.02, 0.02, 0.02]])
    z, s, level = lepski_select(est, se, 2.0)
    assert level.tolist() == [2, 1, 0]
    assert z.tolist() == [0.15, 0.1, 0.0] and s.tolist() == [0.02, 0.05, 0.1]


def test_that_box_sums_and_window_sizes_are_what_they_say():
    a = np.random.default_rng(7).uniform(size=(9, 7))
    for j in (0, 1, 3):
        b = box_sum(a, j)
        for i, k in ((0, 0), (4, 3), (8, 6)):
            assert b[i, k] == pytest.approx(a[max(0, i - j):i + j + 1, max(0, k - j):k + j + 1].sum())
    assert window_halfwidths(0.25, 2.0) == [0, 1, 2, 4, 8]
    assert window_halfwidths(0.25, 0.0) == [0]


def test_that_one_integral_image_for_the_widest_window_gives_every_narrower_window_the_same_sums_to_the_bit():
    a = np.random.default_rng(8).normal(size=(40, 23)) * 1e3
    integral = integral_image(a, 8)
    for j in (0, 1, 2, 4, 8):
        assert np.array_equal(box_sum(a, j, integral, 8), box_sum(a, j))


def test_that_the_report_fits_local_linear_on_request_with_the_headers_sigmas(tmp_path, capsys):
    from ground.cli import main

    assert main(["report", str(GOLDEN), "--out", str(tmp_path / "ll"), "--no-plots", "--surface-fit", "local-linear",
                 "--truth-volume", "7206.9"]) == 0
    rep = json.loads((tmp_path / "ll" / "report.json").read_text())
    assert rep["surface_fit"] == "local-linear"
    assert main(["report", str(GOLDEN), "--out", str(tmp_path / "cl"), "--no-plots", "--truth-volume", "7206.9"]) == 0
    base = json.loads((tmp_path / "cl" / "report.json").read_text())
    # the golden log is a clean flight: estimating instead of interpolating changes its volume by little
    assert rep["volume_m3"] == pytest.approx(base["volume_m3"], rel=0.01)
    assert base["noise_corrections"] is False
    capsys.readouterr()


def test_that_the_report_takes_off_the_noise_biases_on_request_and_says_so(tmp_path, capsys):
    from ground.cli import main

    assert main(["report", str(GOLDEN), "--out", str(tmp_path / "nc"), "--no-plots", "--noise-corrections",
                 "--truth-volume", "7206.9"]) == 0
    rep = json.loads((tmp_path / "nc" / "report.json").read_text())
    assert rep["noise_corrections"] is True and rep["pointing_bias"] is False
    assert main(["report", str(GOLDEN), "--out", str(tmp_path / "d"), "--no-plots", "--truth-volume", "7206.9"]) == 0
    base = json.loads((tmp_path / "d" / "report.json").read_text())
    # a clean flight: no pointing error to move the points by, and windows that stay narrow: little to take off
    assert rep["volume_m3"] == pytest.approx(base["volume_m3"], rel=0.002)
    capsys.readouterr()


def test_that_degenerate_clouds_give_no_surface_and_no_error():
    line = np.column_stack([np.linspace(0, 10, 20), np.linspace(0, 10, 20), np.ones(20)])
    for pts in (np.zeros((0, 3)), line, line[:2]):
        h, s = fit_heights_with_se(pts, G, "local-linear", np.full(len(pts), 0.1))
        assert np.isnan(h).all() and np.isnan(s).all()


@pytest.mark.parametrize("sigma_m", [None, RES_SIGMA])
def test_that_the_estimated_surface_covers_the_points_hull_as_the_interpolant_does(sigma_m):
    """Nodes at the cells' data centroids alone would stop up to half a cell inside the points' hull; the
    hull's corners carry nodes too, so the estimated surface is defined on the interpolant's cells."""
    rng = np.random.default_rng(4)
    xy = np.column_stack([rng.uniform(0.3, 19.7, 4000), rng.uniform(0.3, 9.7, 4000)])
    pts = np.column_stack([xy, plane(xy)])
    sigma = None if sigma_m is None else np.full(len(pts), sigma_m)
    through = fit_heights(pts, G, "cubic-limited")
    est = fit_heights(pts, G, "local-linear", sigma)
    assert np.array_equal(np.isfinite(est), np.isfinite(through))
    assert np.nanmax(np.abs(est - cell_truth(plane))) < 1e-6  # the corners' planes are exact on a plane too


def test_that_a_hull_corner_whose_cell_has_no_node_adds_none():
    rng = np.random.default_rng(5)
    xy = np.column_stack([rng.uniform(2, 18, 3000), rng.uniform(2, 8, 3000)])
    pts = np.column_stack([xy, np.zeros(len(xy))])
    spike = np.array([[19.6, 9.6, 6.0]])  # a lone point far above its neighbours' plane, alone in its cell
    around = np.array([[19.3, 9.3, 0.0], [19.3, 9.6, 0.0], [19.6, 9.3, 0.0], [19.4, 9.4, 0.0], [19.35, 9.55, 0.0]])
    all_pts = np.vstack([pts, around, spike])
    h = fit_heights(all_pts, G, "local-linear", np.full(len(all_pts), RES_SIGMA))
    assert np.nanmax(h) < 0.01  # the outlier's cell has no node, so its hull corner does not lift the surface


def test_that_a_points_weight_does_not_carry_its_own_range_noise():
    """A flat floor seen at 10 m with 5 % range noise: a sigma from each point's own range would weigh the readings
    that came back long (placed low) less and lift the weighted mean by about 2 sigma^2 / r = 5 cm. Taken from the
    neighbours' median range, the weighted mean stays on the floor within its own standard error."""
    from ground.pointcloud import Cloud, SensorErrorModel
    from ground.smoothing import cloud_vertical_sigma_m

    rng = np.random.default_rng(3)
    n, r0 = 200_000, 10.0
    dirs = np.tile([0.0, 0.0, -1.0], (n, 1))
    r = r0 * (1.0 + 0.05 * rng.standard_normal(n))
    origins = np.column_stack([rng.uniform(0, 20, n), rng.uniform(0, 10, n), np.full(n, r0)])
    cloud = Cloud(origins + dirs * r[:, None], dirs, r, origins, n, 0)
    err = SensorErrorModel(range_sigma_rel=0.05, resolution_m=0.01)
    w = 1.0 / cloud_vertical_sigma_m(cloud, err, np.ones(n, dtype=bool), range_from_neighbours=True) ** 2
    own = 1.0 / cloud_vertical_sigma_m(cloud, err, np.ones(n, dtype=bool)) ** 2  # the default, for now
    mean, mean_own = np.average(cloud.points_w[:, 2], weights=w), np.average(cloud.points_w[:, 2], weights=own)
    assert mean_own > 0.04  # the bias this removes, as the rule of thumb says
    assert abs(mean) < 4 * 0.05 * r0 / math.sqrt(n)  # 4 standard errors of the mean: 4.5 mm

