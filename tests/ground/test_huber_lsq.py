"""The robust sparse least squares of the pose correction's linear fits (ground/huber_lsq.py)."""

import math

import numpy as np
import pytest
from scipy import sparse
from scipy.sparse.linalg import spsolve

from ground.huber_lsq import coupled_columns, irls_huber, knot_covariance, mean_sigma_m, weighted_solver


def test_that_the_robust_fits_solve_is_the_general_sparse_solution_with_or_without_cells_to_eliminate():
    rng = np.random.default_rng(3)
    n_knots, n_cells, m = 12, 200, 900
    knot = rng.integers(0, n_knots - 1, m)
    cell = rng.integers(0, n_cells, m)
    rows = np.repeat(np.arange(m), 3)
    cols = np.column_stack([knot, knot + 1, n_knots + cell]).ravel()
    obs = sparse.csr_matrix((rng.normal(size=3 * m), (rows, cols)), shape=(m, n_knots + n_cells))
    structured = sparse.vstack([obs, sparse.identity(n_knots + n_cells)], format="csr")  # a prior on every one
    n = n_knots + n_cells  # a row holding two cells (the last two): no diagonal block left to eliminate
    tangled = sparse.vstack([structured, sparse.csr_matrix(([1.0, -1.0], ([0, 0], [n - 2, n - 1])), shape=(1, n))],
                            format="csr")
    # rows on two components' knots (as the registration's: x and heading)
    other = rng.integers(0, n_knots // 2 - 1, m)
    cols4 = np.column_stack([other, other + 1, n_knots // 2 + other, n_knots // 2 + other + 1, n_knots + cell]).ravel()
    obs4 = sparse.csr_matrix((rng.normal(size=5 * m), (np.repeat(np.arange(m), 5), cols4)), shape=(m, n))
    several = sparse.vstack([obs4, sparse.identity(n)], format="csr")
    assert coupled_columns(structured) == n_knots and coupled_columns(tangled) == n - 1
    for a in (structured, tangled, several):
        rhs = rng.normal(size=a.shape[0])
        w = rng.uniform(0.1, 1.0, a.shape[0])
        aw = a.multiply(np.sqrt(w)[:, None]).tocsr()
        want = spsolve((aw.T @ aw).tocsc(), aw.T @ (np.sqrt(w) * rhs))
        assert np.allclose(weighted_solver(a, rhs)(w), want, atol=1e-9)


def test_that_the_height_s_standard_error_is_that_of_the_mean_of_its_rows():
    # one knot seen by n rows of one sigma each (the rows are in units of their sigma): the mean's standard error is
    # sigma / sqrt(n); a row the robust fit weighs down counts less
    sigma, n = 0.02, 25
    rng = np.random.default_rng(3)
    y = rng.uniform(-0.5 * sigma, 0.5 * sigma, n)
    a = sparse.csr_matrix(np.full((n, 1), 1.0 / sigma))
    x = np.array([y.mean()])
    basis = (np.zeros(10, dtype=np.int64), np.zeros(10))
    assert mean_sigma_m(a, x, y / sigma, basis, 1) == pytest.approx(sigma / math.sqrt(n))
    y_out = y.copy()
    y_out[0] = 10.0 * sigma  # an outlier: Huber weight 1 / |r|
    assert mean_sigma_m(a, x, y_out / sigma, basis, 1) > sigma / math.sqrt(n)


def test_that_the_knots_covariance_says_how_loosely_two_stretches_of_the_flight_are_tied():
    """Knots 0-1 and 2-3 tied tightly by what they saw (rows in units of their sigma: 1 cm), 1 to 2 only by a prior
    of 1 m: the covariance lets 2 float against 1 by the prior's metre, 1 against 0 by a centimetre."""
    rows = [(0, 1, 100.0), (2, 3, 100.0), (1, 2, 1.0)]  # (knot, next knot, 1/sigma) of their difference
    a = sparse.lil_matrix((len(rows) + 1, 4))
    for i, (j, k, w) in enumerate(rows):
        a[i, j], a[i, k] = -w, w
    a[len(rows), 0] = 100.0  # the level, pinned at knot 0
    c = knot_covariance(a.tocsr(), np.zeros(4), np.zeros(len(rows) + 1), 4)

    def sd(i: int, j: int) -> float:
        return math.sqrt(c[i, i] + c[j, j] - 2.0 * c[i, j])
    assert sd(0, 1) == pytest.approx(0.01, rel=1e-6)
    assert sd(1, 2) == pytest.approx(1.0, rel=1e-3) and sd(2, 3) == pytest.approx(0.01, rel=1e-6)
    np.testing.assert_allclose(c, c.T, atol=1e-15)
    # a knot nothing observes and no prior holds: no covariance, rather than an error or a NaN that drops every
    # floor candidate against it
    loose = sparse.csr_matrix(a.toarray()[:, :3])
    assert knot_covariance(sparse.hstack([loose, sparse.csr_matrix((len(rows) + 1, 1))]).tocsr(), np.zeros(4),
                           np.zeros(len(rows) + 1), 4) is None


def test_that_the_robust_fit_is_least_squares_on_clean_rows_and_shrugs_off_a_gross_error():
    rng = np.random.default_rng(5)
    x_true = np.array([0.3, -1.2])
    a = sparse.csr_matrix(np.column_stack([np.ones(40), np.linspace(-1.0, 1.0, 40)]))
    rhs = a @ x_true + rng.uniform(-0.5, 0.5, 40)  # within Huber's corner: every row weighs fully
    np.testing.assert_allclose(irls_huber(a, rhs), np.linalg.lstsq(a.toarray(), rhs, rcond=None)[0], atol=1e-9)
    rhs[7] += 200.0  # one gross error
    least = np.linalg.lstsq(a.toarray(), rhs, rcond=None)[0]
    robust = irls_huber(a, rhs)
    assert np.max(np.abs(robust - x_true)) < 0.25 < np.max(np.abs(least - x_true))
