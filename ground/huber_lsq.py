"""Robust sparse least squares: Huber's loss minimised by iteratively re-weighted normal equations, and what the
fit's normal equations at its solution say of its unknowns (a mean's standard error, the leading unknowns'
covariance).

The pose correction's linear fits (the height from the pile seen at different times, the registration on it) have
one shape: a few leading unknowns that many rows share (the trajectory's knots) and many trailing ones that meet only
those (the cells' heights), so the normal equations' trailing block is diagonal and is eliminated exactly (a Schur
complement, `weighted_solver`). Rows come in units of their sigma: Huber's corner is at 1 (or `scale`)."""

from __future__ import annotations

import math

import numpy as np
from scipy import linalg, sparse
from scipy.sparse.linalg import splu, spsolve


def huber_normal(a: sparse.csr_matrix, x: np.ndarray, rhs: np.ndarray) -> sparse.csc_matrix:
    """The robust fit's normal equations at its solution x: the rows (in units of their sigma) weighed as Huber's loss
    weighs them there (`irls_huber`'s last weights), A^T W A, ready to factorise."""
    r = np.abs(a @ x - rhs)
    w = np.where(r <= 1.0, 1.0, 1.0 / np.maximum(r, 1e-300))
    aw = a.multiply(np.sqrt(w)[:, None]).tocsr()
    return (aw.T @ aw).tocsc()


def mean_sigma_m(a: sparse.csr_matrix, x: np.ndarray, rhs: np.ndarray, basis: tuple[np.ndarray, np.ndarray],
                 n_knots: int) -> float:
    """The standard error of the height correction's mean over the samples (basis: their knot and fraction), from
    the robust fit's normal equations at its solution (`irls_huber`'s last weights; the rows in units of their
    sigma): what a height error common to the whole survey, the one that moves the volume, the data leave. Formal:
    it assumes the cells' heights independent, which a stretch of the flight misplaced on slopes is not, so the
    interval scales it by a factor calibrated on drifting flights (ground.uncertainty)."""
    k, f = basis
    w_k = (np.bincount(k, weights=1.0 - f, minlength=n_knots + 1)
           + np.bincount(k + 1, weights=f, minlength=n_knots + 1))[:n_knots]
    e = np.zeros(a.shape[1])
    e[:n_knots] = w_k / max(float(w_k.sum()), 1e-300)
    u = spsolve(huber_normal(a, x, rhs), e)
    return float(math.sqrt(max(float(e @ u), 0.0)))


def knot_covariance(a: sparse.csr_matrix, x: np.ndarray, rhs: np.ndarray, n_knots: int) -> np.ndarray | None:
    """(K, K) the knots' covariance from the robust fit's normal equations at its solution (as `mean_sigma_m`, the rows
    in units of their sigma): how loosely the data tie one stretch of the flight's height to another. None when the
    equations are singular or give no finite answer (the caller then judges as if every stretch were tied)."""
    e = np.zeros((a.shape[1], n_knots))
    e[np.arange(n_knots), np.arange(n_knots)] = 1.0
    try:
        u = splu(huber_normal(a, x, rhs)).solve(e)[:n_knots]
    except RuntimeError:  # "Factor is exactly singular"
        return None
    return u if np.all(np.isfinite(u)) else None


def huber_loss(u: np.ndarray) -> np.ndarray:
    """Huber's loss of residuals in units of their sigma: quadratic within 1, linear beyond (a gross error weighs
    as its size, not its square)."""
    a = np.abs(u)
    return np.where(a <= 1.0, 0.5 * a * a, a - 0.5)


IRLS_ROUNDS = 20
"""The robust fits' rounds. On the drifting flights they end here, not at their 1e-6 tolerance: the knots still move
0.1-0.7 mm a round and lie 0.4-7 mm from the Huber cost's minimum, so the fit is part way from least squares to
it. Run further towards it (200 rounds) or to it (Newton's method on the active set), the campaigns read worse,
not better (paper piles within 0.3 pp 18 -> 16 of 38, one flight 0.2 -> 5.5 pp): the stop is load-bearing, and was
measured, not chosen (docs/design-notes.md, "The robust fits stop short of their minimum")."""


def irls_huber(a: sparse.csr_matrix, rhs: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """argmin sum huber(a x - rhs) for a linear, sparse problem, approached by iteratively re-weighted normal
    equations from least squares (a direct solve each round; the trust-region solver crawled on this one), for at
    most IRLS_ROUNDS rounds (which on drifting flights end before the minimum: see there)."""
    w = np.ones(a.shape[0])
    x = np.zeros(a.shape[1])
    solve = weighted_solver(a.tocsr(), rhs)
    for _ in range(IRLS_ROUNDS):
        x_new = solve(w)
        r = np.abs(a @ x_new - rhs)
        w = np.where(r <= scale, 1.0, scale / np.maximum(r, 1e-300))
        if np.max(np.abs(x_new - x)) < 1e-6:
            return x_new
        x = x_new
    return x


def weighted_solver(a: sparse.csr_matrix, rhs: np.ndarray):
    """w -> argmin sum w (a x - rhs)^2. The problems here are knots (the leading columns) and cells' heights
    (the rest), and no row holds two cells, so the normal equations' cell block is diagonal: the cells are
    eliminated (a Schur complement) and the knots solved densely. Exact, and 3-5x faster than a general sparse
    solve on a flight's ~1,000 unknowns. Which entries meet which is the same every round, only the weights change:
    the products' index pairs are found once here (`row_pairs`) and each round only sums weighted terms into them
    (`np.bincount`): 0.3-0.4 ms a solve against 1.0-1.1 ms through scipy.sparse's products, on the quiet
    machine (docs/design-notes.md)."""
    def general(w: np.ndarray) -> np.ndarray:
        aw = a.multiply(np.sqrt(w)[:, None]).tocsr()
        return spsolve((aw.T @ aw).tocsc(), aw.T @ (np.sqrt(w) * rhs))
    lead = coupled_columns(a)
    n = a.shape[1]
    if lead > n // 2:  # no such structure
        return general
    canonical = sparse.csr_matrix(a, copy=True)
    canonical.sum_duplicates()
    cells, knots = canonical[:, lead:].tocoo(), canonical[:, :lead].tocoo()
    row, col, val = cells.row, cells.col, cells.data
    kr, kk, kv = knots.row, knots.col, knots.data
    n_c = n - lead

    def cells_alone(w: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:  # the cell block's diagonal and rhs
        wv = w[row] * val
        d = np.bincount(col, weights=wv * val, minlength=n_c)
        # a cell without a row of weight: not this structure after all (None)
        return (d, np.bincount(col, weights=wv * rhs[row], minlength=n_c)) if np.all(d > 0) else None

    if lead == 0:
        def diagonal(w: np.ndarray) -> np.ndarray:
            found = cells_alone(w)
            return general(w) if found is None else found[1] / found[0]
        return diagonal
    i, j = row_pairs(kr, kr)  # the knots' own block: a_k' W a_k
    kk_flat, kk_coef, kk_row = kk[i] * lead + kk[j], kv[i] * kv[j], kr[i]
    i, e = row_pairs(kr, row)  # g = a_k' W a_c: the knots x cells block, on its nonzero pattern
    g_flat, g_of = np.unique(kk[i] * n_c + col[e], return_inverse=True)
    gk, gc = np.divmod(g_flat, n_c)
    g_coef, g_row = kv[i] * val[e], kr[i]
    p, q = row_pairs(gc, gc)  # g D^-1 g': the pairs of g's entries on one cell
    gg_flat = gk[p] * lead + gk[q]

    def schur(w: np.ndarray) -> np.ndarray:
        found = cells_alone(w)
        if found is None:
            return general(w)
        d, b_c = found
        g = np.bincount(g_of, weights=g_coef * w[g_row], minlength=len(g_flat))
        s = (np.bincount(kk_flat, weights=kk_coef * w[kk_row], minlength=lead * lead)
             - np.bincount(gg_flat, weights=g[p] * g[q] / d[gc[p]], minlength=lead * lead)).reshape(lead, lead)
        r = (np.bincount(kk, weights=kv * (w * rhs)[kr], minlength=lead)
             - np.bincount(gk, weights=g * (b_c / d)[gc], minlength=lead))
        try:
            x_k = linalg.solve(s, r, assume_a="pos")
        except linalg.LinAlgError:  # not positive definite to working precision
            x_k = linalg.lstsq(s, r)[0]
        return np.concatenate([x_k, (b_c - np.bincount(gc, weights=g * x_k[gk], minlength=n_c)) / d])
    return schur


def row_pairs(rows_1: np.ndarray, rows_2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every pair (i, j) of an entry i of one list and j of another that share a row (rows_1[i] == rows_2[j]):
    the terms of a product of two sparse matrices' columns, found once and summed each round."""
    order = np.argsort(rows_2, kind="stable")
    sorted_2 = rows_2[order]
    start = np.searchsorted(sorted_2, rows_1, "left")
    count = np.searchsorted(sorted_2, rows_1, "right") - start
    i = np.repeat(np.arange(len(rows_1)), count)
    within = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
    return i, order[np.repeat(start, count) + within]


def coupled_columns(a: sparse.csr_matrix) -> int:
    """How many leading columns of a share rows with other columns: after them each column (a cell's height)
    meets only the leading ones (the knots), so the normal equations' trailing block is diagonal."""
    coo = (a.T @ a).tocoo()
    off = coo.row != coo.col
    return int(np.minimum(coo.row, coo.col)[off].max()) + 1 if off.any() else 0
