"""The cubic's slopes at its nodes from a Gaussian process (ground.gp_slopes, `SmoothingOptions.slopes`)."""

from collections import OrderedDict

import numpy as np
import pytest
from scipy.interpolate import CloughTocher2DInterpolator

from ground.gp_slopes import (
    CANDIDATES,
    FIRST_CANDIDATES,
    MIN_NODES,
    PER_OCTANT,
    GpCovariance,
    _neighbourhoods,
    bridge_nodes,
    fit_covariance,
    gp_smoothed,
    matern52,
    node_slopes,
    octant_neighbours,
    restricted_loglik,
)
from ground.smoothing import NodeSlopes, SmoothingOptions
from ground.surface import Grid, fit_heights, grid_volume
from ground.triangulation import delaunay


def hill(xy):
    """A smooth mound 3 m high, 6 m wide, in a 30 x 20 m floor."""
    return 3.0 * np.exp(-((xy[:, 0] - 15.0) ** 2 + (xy[:, 1] - 10.0) ** 2) / (2 * 3.0**2))


def hill_slope(xy):
    h = hill(xy)
    return np.column_stack([-h * (xy[:, 0] - 15.0) / 9.0, -h * (xy[:, 1] - 10.0) / 9.0])


def fan_lines(spacing_m=3.0, step_m=0.25):
    """Nodes along lines across a 30 x 20 m floor, `spacing_m` apart and `step_m` along: a sparse flight's swaths."""
    xs = np.arange(1.0, 29.5, spacing_m)
    ys = np.arange(0.5, 19.6, step_m)
    return np.array([(x, y) for x in xs for y in ys])


def scipy_slopes(xy, z):
    return CloughTocher2DInterpolator(delaunay(np.ascontiguousarray(xy)), z).grad[:, 0, :]


def slopes(xy, z, se):
    return node_slopes(delaunay(np.ascontiguousarray(xy)), z, se)


def rms(g, xy):
    return float(np.sqrt(np.mean(np.sum((g - hill_slope(xy)) ** 2, axis=1))))


def test_that_the_predicted_heights_of_a_plane_are_the_planes_own_whatever_the_covariance():
    xy = fan_lines()
    z = 1.0 + 0.3 * xy[:, 0] - 0.2 * xy[:, 1]
    for cov in (GpCovariance(1.0, 0.1), GpCovariance(16.0, 5.0)):
        np.testing.assert_allclose(gp_smoothed(xy, z, np.full(len(z), 1e-4), cov), z, atol=1e-6)


def test_that_noise_free_nodes_keep_their_heights_and_scipys_slopes():
    xy = fan_lines()
    z = hill(xy)
    se = np.full(len(z), 0.001)  # a range quantum's error
    cov = fit_covariance(xy, z, se**2)
    assert np.max(np.abs(gp_smoothed(xy, z, se**2, cov) - z)) < 3 * 0.001
    np.testing.assert_allclose(slopes(xy, z, se), scipy_slopes(xy, z), atol=0.01)


def test_that_noisy_nodes_get_slopes_nearer_the_truth_than_scipys():
    xy = fan_lines()
    rng = np.random.default_rng(3)
    se = np.full(len(xy), 0.03)
    z = hill(xy) + rng.normal(0.0, 0.03, len(xy))
    exact = fit_covariance(xy, hill(xy), np.full(len(xy), 0.001) ** 2)
    assert fit_covariance(xy, z, se**2).length_m < exact.length_m  # the noise is averaged over a shorter reach
    err_gp, err_scipy = rms(slopes(xy, z, se), xy), rms(scipy_slopes(xy, z), xy)
    assert err_gp < 0.5 * err_scipy, (err_gp, err_scipy)


def test_that_the_slopes_are_the_same_for_the_same_nodes():
    xy = fan_lines()
    rng = np.random.default_rng(4)
    z = hill(xy) + rng.normal(0.0, 0.03, len(xy))
    se = np.full(len(z), 0.03)
    np.testing.assert_array_equal(slopes(xy, z, se), slopes(xy, z, se))


def test_that_each_octant_gives_its_nearest_nodes_and_the_node_itself_is_kept():
    xy = fan_lines(spacing_m=3.0)
    at = xy[[100]]
    idx, valid = octant_neighbours(xy, at, per=2)
    got = idx[0][valid[0]]
    assert 100 in got
    d = xy[got] - at[0]
    assert np.any(np.abs(d[:, 0]) > 2.0)  # the next line's nodes, though the nearest 17 all lie on its own line
    assert len(got) <= 8 * 2 + 1


def brute_force_octants(xy, p, per):
    """The octant neighbours of p by brute force: the node at p, and the `per` nearest of each direction among the
    CANDIDATES nearest nodes."""
    d = xy - p
    r = np.hypot(d[:, 0], d[:, 1])
    octant = np.floor((np.arctan2(d[:, 1], d[:, 0]) + np.pi) / (np.pi / 4)).astype(int) % 8
    pool = np.zeros(len(xy), dtype=bool)
    pool[np.argsort(r, kind="stable")[:CANDIDATES]] = True  # the octants are filled from the nearest candidates
    want = {int(j) for j in np.flatnonzero(r < 1e-9)}
    for o in range(8):
        members = np.flatnonzero((octant == o) & (r >= 1e-9) & pool)
        want |= {int(j) for j in members[np.argsort(r[members], kind="stable")][:per]}
    return want


def test_that_each_octant_holds_exactly_its_nearest_candidates():
    rng = np.random.default_rng(5)
    xy = rng.uniform(0.0, 20.0, (400, 2))
    at = np.concatenate([xy[:20], rng.uniform(0.0, 20.0, (20, 2))])  # on a node (kept itself) and between nodes
    idx, valid = octant_neighbours(xy, at, per=3)
    for i, p in enumerate(at):
        assert set(idx[i][valid[i]].tolist()) == brute_force_octants(xy, p, 3)


def test_that_a_node_whose_octants_its_first_candidates_leave_empty_is_looked_up_among_all_of_them():
    xy = fan_lines(spacing_m=3.0, step_m=0.05)  # the nearest FIRST_CANDIDATES of a node all lie on its own line,
    at = xy[(xy[:, 1] > 5.0) & (xy[:, 1] < 15.0)][::50]  # away from its ends, but not its nearest CANDIDATES
    d = xy[:, None, :] - at[None]
    first = np.argsort(np.hypot(d[..., 0], d[..., 1]), axis=0, kind="stable")[:FIRST_CANDIDATES]
    assert np.all(np.abs(xy[first, 0] - at[:, 0]) < 1e-9)  # the first look holds none of the next line's nodes
    idx, valid = octant_neighbours(xy, at)
    for i, p in enumerate(at):
        got = set(idx[i][valid[i]].tolist())
        assert got == brute_force_octants(xy, p, PER_OCTANT)
        assert np.any(np.abs(xy[list(got), 0] - p[0]) > 2.0)  # the next lines' nodes are among them


def two_blocks(gap_m=5.0, step_m=0.25):
    """Two dense 5 x 10 m blocks of nodes with a gap_m strip between them, along x."""
    xs = np.arange(0.0, 5.0 + 1e-9, step_m)
    ys = np.arange(0.0, 10.0 + 1e-9, step_m)
    block = np.array([(x, y) for x in xs for y in ys])
    return np.concatenate([block, block + np.array([5.0 + gap_m, 0.0])])


def test_that_the_bridge_nodes_are_the_corners_of_the_triangles_longer_than_the_reach_and_their_neighbours():
    xy = two_blocks()
    tri = delaunay(xy)
    got = set(bridge_nodes(tri, 2.0).tolist())
    pts = xy[tri.simplices]
    longest = np.max(np.linalg.norm(pts - np.roll(pts, 1, axis=1), axis=2), axis=1)
    corners = set(tri.simplices[longest > 2.0].ravel().tolist())
    indptr, indices = tri.vertex_neighbor_vertices
    want = corners | {int(j) for v in corners for j in indices[indptr[v]:indptr[v + 1]]}
    assert got == want
    x = xy[sorted(got), 0]
    assert np.all((np.abs(x - 5.0) <= 0.5) | (np.abs(x - 10.0) <= 0.5))  # the blocks' facing edges only
    assert bridge_nodes(tri, 6.0).size == 0  # no triangle spans further than 6 m


def test_that_nodes_whose_triangles_all_stay_within_the_reach_keep_scipys_slopes():
    xy = two_blocks(gap_m=0.25)  # one dense block: no triangle longer than the windows reach
    z = hill(xy) + np.random.default_rng(6).normal(0.0, 0.03, len(xy))
    assert node_slopes(delaunay(xy), z, np.full(len(z), 0.03), reach_m=2.0) is None


def test_that_where_every_triangle_bridges_a_gap_the_bridges_slopes_are_the_gps():
    xy = fan_lines(spacing_m=3.0)  # every triangle spans from one line to the next, 3 m
    z = hill(xy) + np.random.default_rng(7).normal(0.0, 0.03, len(xy))
    se = np.full(len(z), 0.03)
    tri = delaunay(xy)
    assert len(bridge_nodes(tri, 2.0)) == len(xy)
    np.testing.assert_array_equal(node_slopes(tri, z, se, reach_m=2.0), node_slopes(tri, z, se))


def test_that_the_bridges_slopes_are_nearer_the_truth_than_scipys_across_a_gap():
    xy = two_blocks(gap_m=4.0)
    xy = xy + np.array([8.0, 5.0])  # the hill's crest (15, 10) in the gap, x 13-17
    rng = np.random.default_rng(8)
    se = np.full(len(xy), 0.03)
    z = hill(xy) + rng.normal(0.0, 0.03, len(xy))
    tri = delaunay(xy)
    edge = bridge_nodes(tri, 2.0)
    err_bridges = rms(node_slopes(tri, z, se, reach_m=2.0)[edge], xy[edge])
    err_scipy = rms(scipy_slopes(xy, z)[edge], xy[edge])
    assert err_bridges < 0.5 * err_scipy, (err_bridges, err_scipy)


def test_that_too_few_nodes_or_errors_that_are_not_numbers_keep_scipys_slopes():
    xy = fan_lines()
    z = hill(xy)
    few = np.linspace(0, len(z) - 1, MIN_NODES - 1).astype(int)  # spread over the lines, so that they triangulate
    assert slopes(xy[few], z[few], np.full(len(few), 0.01)) is None
    bad = np.full(len(z), 0.01)
    bad[5] = np.nan
    assert slopes(xy, z, bad) is None
    bad[5] = -0.01
    assert slopes(xy, z, bad) is None


def test_that_nodes_the_process_cannot_fit_keep_scipys_slopes_and_raise_nothing():
    xy = np.column_stack([np.arange(200) * 0.25, np.zeros(200)])  # one line: no plane through any neighbourhood
    xy = np.concatenate([xy, [[10.0, 5.0], [20.0, -5.0]]])  # and two nodes off it, so that it triangulates
    z = np.sin(xy[:, 0])
    got = slopes(xy, z, np.zeros(len(z)))  # exact heights, no noise: nothing keeps the systems regular
    assert got is None or np.all(np.isfinite(got))


def test_that_the_slopes_option_is_checked():
    assert SmoothingOptions(slopes="gp").slopes is NodeSlopes.GP
    with pytest.raises(ValueError, match="node slopes must be one of curvature, gp"):
        SmoothingOptions(slopes="kriging")


def test_that_with_gp_slopes_the_volume_between_noisy_fan_lines_is_nearer_the_truth():
    grid = Grid(30, 20, 0.25)
    cx, cy = grid.centres()
    true = grid_volume(hill(np.column_stack([cx.ravel(), cy.ravel()])).reshape(cx.shape), grid)
    errors = {NodeSlopes.GP: [], NodeSlopes.CURVATURE: []}
    for seed in range(6):  # one draw can favour either: the error's spread over draws is what the slopes change
        rng = np.random.default_rng(seed)
        base = fan_lines(spacing_m=4.0, step_m=0.05)
        pts = base + rng.normal(0.0, 0.02, base.shape)
        points = np.column_stack([pts, hill(pts) + rng.normal(0.0, 0.05, len(pts))])
        for slopes_from, out in errors.items():
            h = fit_heights(points, grid, "local-linear", np.full(len(pts), 0.05), SmoothingOptions(slopes=slopes_from))
            out.append(grid_volume(np.where(np.isfinite(h), h, 0.0), grid) - true)
    rms = {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in errors.items()}
    assert rms[NodeSlopes.GP] < 0.5 * rms[NodeSlopes.CURVATURE], rms


def test_that_the_smoothed_heights_do_not_depend_on_how_many_nodes_are_solved_at_once(monkeypatch):
    import ground.gp_slopes as gp

    xy = fan_lines()
    z = hill(xy) + np.random.default_rng(3).normal(0.0, 0.05, len(xy))
    var = np.full(len(xy), 0.05**2)
    cov = GpCovariance(2.0, 1.0)
    whole = gp_smoothed(xy, z, var, cov)
    monkeypatch.setattr(gp, "CHUNK", 37)  # chunks that do not divide the nodes
    assert np.array_equal(gp_smoothed(xy, z, var, cov), whole)


def test_that_the_heights_and_the_covariance_are_the_same_on_one_thread_or_several(monkeypatch):
    import ground.gp_slopes as gp

    xy = fan_lines()
    z = hill(xy) + np.random.default_rng(4).normal(0.0, 0.05, len(xy))
    var = np.full(len(xy), 0.05**2)
    results = {}
    for threads in (1, 3):
        monkeypatch.setattr(gp, "_threads", lambda n=threads: n)
        monkeypatch.setattr(gp, "CHUNK", 37)  # many chunks, finishing in any order
        cov = fit_covariance(xy, z, var)
        results[threads] = (cov, gp_smoothed(xy, z, var, cov))
    assert results[1][0] == results[3][0]
    assert np.array_equal(results[1][1], results[3][1])


def textbook_loglik(xy, z, var, at, idx, valid, cov):
    """The restricted log-likelihood of each neighbourhood's filled slots, written out: the covariance, a plane's
    drift through the slots' offsets, the generalised least-squares plane, and the two determinants."""
    total = 0.0
    for p, slots in zip(at, [i[v] for i, v in zip(idx, valid, strict=True)], strict=True):
        d = xy[slots] - p
        r = np.hypot(d[:, None, 0] - d[None, :, 0], d[:, None, 1] - d[None, :, 1])
        s2 = cov.amplitude_m**2
        c = s2 * matern52(r / cov.length_m) + np.diag(var[slots] + 1e-10 * s2)
        f = np.column_stack([np.ones(len(slots)), d])
        ci = np.linalg.inv(c)
        beta = np.linalg.solve(f.T @ ci @ f, f.T @ ci @ z[slots])
        res = z[slots] - f @ beta
        total += -0.5 * (res @ ci @ res + np.linalg.slogdet(c)[1] + np.linalg.slogdet(f.T @ ci @ f)[1])
    return total


def test_that_the_restricted_likelihood_is_the_textbook_formula_summed_over_the_neighbourhoods():
    xy = fan_lines()
    rng = np.random.default_rng(5)
    var = rng.uniform(0.01, 0.05, len(xy)) ** 2
    z = hill(xy) + rng.normal(0.0, np.sqrt(var))
    at = np.array([[15.2, 10.1], [4.0, 3.0], [0.2, 0.1], [28.9, 19.8]])  # inside, and corners that leave octants empty
    idx, valid = octant_neighbours(xy, at)
    assert not valid.all()
    nb = _neighbourhoods(xy, at, idx, valid)
    # The empty slots stay in the function's systems with a variance of 1e6: their pull on the plane is a part in
    # a million (3e-5 of 146 here), which is what the tolerance allows.
    for cov in (GpCovariance(3.0, 0.5), GpCovariance(0.5, 0.02), GpCovariance(32.0, 10.0)):
        assert restricted_loglik(nb, z, var, cov) == pytest.approx(textbook_loglik(xy, z, var, at, idx, valid, cov),
                                                                   rel=1e-6)


@pytest.mark.parametrize("offset_m", [0.0, 40.0])
def test_that_the_likelihood_through_the_bordered_factor_holds_for_noise_free_nodes_high_above_their_origin(offset_m):
    """Noise-free nodes make the worst conditioned covariances, and heights far from the drift's plane the largest
    forward substitution: the corner below them (`HEIGHTS_CORNER`) must stay above what they add."""
    xy = fan_lines()
    z = hill(xy) * 40.0 + offset_m
    var = np.zeros(len(xy))
    at = np.array([[15.2, 10.1], [4.0, 3.0]])
    idx, valid = octant_neighbours(xy, at)
    nb = _neighbourhoods(xy, at, idx, valid)
    for cov in (GpCovariance(64.0, 0.01), GpCovariance(0.25, 40.96)):
        got = restricted_loglik(nb, z, var, cov)
        assert np.isfinite(got)
        assert got == pytest.approx(textbook_loglik(xy, z, var, at, idx, valid, cov), rel=1e-6)


def test_that_a_covariance_that_is_not_positive_definite_or_nodes_on_one_line_are_no_candidate():
    xy = fan_lines()
    z = hill(xy)
    at = xy[[100, 300]]
    nb = _neighbourhoods(xy, at, *octant_neighbours(xy, at))
    assert restricted_loglik(nb, z, np.full(len(z), -1.0), GpCovariance(3.0, 0.5)) == -np.inf  # negative variances
    line = np.column_stack([np.linspace(0.0, 10.0, 80), np.zeros(80)])
    at = line[[40]]
    nb = _neighbourhoods(line, at, *octant_neighbours(line, at))
    assert restricted_loglik(nb, line[:, 0], np.full(80, 1e-4), GpCovariance(3.0, 0.5)) == -np.inf  # no plane


def test_that_a_systems_array_reused_from_another_covariance_gives_the_same_likelihood():
    xy = fan_lines()
    z = hill(xy) + np.random.default_rng(6).normal(0.0, 0.03, len(xy))
    var = np.full(len(z), 0.03**2)
    at = np.array([[15.2, 10.1], [0.2, 0.1]])
    nb = _neighbourhoods(xy, at, *octant_neighbours(xy, at))
    k = nb.idx.shape[1]
    cov = GpCovariance(3.0, 0.5)
    alone = restricted_loglik(nb, z, var, cov)
    scratch = np.full((len(at), k + 4, k + 4), np.nan)  # what no element of the systems may keep
    assert restricted_loglik(nb, z, var, cov, scratch=scratch) == alone
    restricted_loglik(nb, z, var, GpCovariance(32.0, 10.0), scratch=scratch)
    assert restricted_loglik(nb, z, var, cov, scratch=scratch) == alone


@pytest.fixture
def counted_fits(monkeypatch):
    """The fits `fitted_covariance` makes, counted, with nothing remembered from other tests."""
    import ground.gp_slopes as gp

    calls = []
    real = gp.fit_covariance
    monkeypatch.setattr(gp, "fit_covariance", lambda *a, **k: calls.append(1) or real(*a, **k))
    monkeypatch.setattr(gp, "_fits", OrderedDict())
    return gp, calls, real


def noisy_hill(seed):
    xy = fan_lines()
    return xy, hill(xy) + np.random.default_rng(seed).normal(0.0, 0.03, len(xy)), np.full(len(xy), 0.03**2)


def test_that_the_same_nodes_get_the_remembered_covariance_without_a_second_fit(counted_fits):
    gp, calls, real = counted_fits
    xy, z, var = noisy_hill(7)
    first = gp.fitted_covariance(xy, z, var)
    assert first == real(xy, z, var)
    assert gp.fitted_covariance(xy.copy(), z.copy(), var.copy()) == first and len(calls) == 1
    nudged = z.copy()
    nudged[7] = np.nextafter(nudged[7], np.inf)  # one height one bit apart: other nodes, fitted again
    gp.fitted_covariance(xy, nudged, var)
    gp.fitted_covariance(xy, z, var * 2.0)
    assert len(calls) == 3


def test_that_only_the_last_fits_are_remembered(counted_fits, monkeypatch):
    gp, calls, _ = counted_fits
    monkeypatch.setattr(gp, "REMEMBERED_FITS", 2)
    sets = [noisy_hill(seed) for seed in (8, 9, 10)]
    for nodes in sets:
        gp.fitted_covariance(*nodes)
    gp.fitted_covariance(*sets[2])  # still remembered
    assert len(calls) == 3
    gp.fitted_covariance(*sets[0])  # the oldest was let go
    assert len(calls) == 4 and len(gp._fits) == 2


def test_that_forgotten_fits_are_fitted_again(counted_fits):
    """What a benchmark calls before each report it times, so that it times the fit a new flight pays for."""
    gp, calls, _ = counted_fits
    nodes = noisy_hill(11)
    gp.fitted_covariance(*nodes)
    gp.forget_fits()
    gp.fitted_covariance(*nodes)
    assert len(calls) == 2
