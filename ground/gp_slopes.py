"""The slopes the surface's cubic takes at its nodes, through node heights a Gaussian process has freed of their noise.

Between the fan lines of a sparse flight the surface is the Clough-Tocher cubic through the estimated nodes
(`ground.surface`), and far from any node it is made of the nodes' *slopes* more than of their heights. scipy
estimates those slopes by making the whole surface as little curved as it can through the node heights, each
taken as exact. Under a degree of pointing noise the nodes along a fan line, a quarter of a metre apart, disagree
by centimetres, and a slope built on those differences is off by a tenth or more; carried 2-4 m across a gap it
is decimetres of height. Measured on the paper's pile 1 at P_traj 30 % under Appendix A's noise: the cells
between fan lines carry a signed volume error of -0.8 +- 1.2 % against -0.2 +- 0.2 % without noise
(docs/design-notes.md, "Slopes through heights a Gaussian process smoothed").

Here the slopes are scipy's, but through the heights the best linear unbiased predictor gives at the nodes
(universal kriging: a Matern 5/2 covariance, a local plane as the drift, each node's own error variance on the
diagonal, from the nodes around each node chosen by octant so that a node on a fan line also sees the next line).
The node heights themselves stay as estimated: only the slopes change. The covariance's length and amplitude are
fitted to the nodes by restricted maximum likelihood over sampled neighbourhoods: noise-free nodes give a
covariance under which the predictor returns each node's own height (so the slopes are scipy's, unchanged), noisy
ones a short, low one that averages their noise out. Nothing is tuned to a pile; the smoothing follows the errors
the header states. Predicting the slopes directly from the process (its gradient) was measured too: it smoothed
the noise as well but took noise-free slopes from scipy's better interpolant (pile 1 at 30 % without noise, mean
|Ve| 0.20 -> 0.42 %).
"""

from __future__ import annotations

import hashlib
import math
import threading
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CloughTocher2DInterpolator
from scipy.spatial import Delaunay, cKDTree

from ground.figure_jobs import cores_available

PER_OCTANT = 4
"""Nodes taken from each of the eight directions around a node (32 and the node itself): enough for the local
plane to be fitted across a gap between fan lines, where the nearest 32 nodes would all lie on one line. Six (48)
gave the same volumes over the evaluation set's runs and their noise-free twins (every P_traj 5-35 %, each noise
model within 0.08 pp) for twice the time (docs/design-notes.md, "Four nodes an octant")."""
CANDIDATES = 160
"""Nearest nodes the octants are filled from."""
FIRST_CANDIDATES = 96
"""Nearest nodes looked at first (`octant_neighbours`): on a P_traj 5 % flight's 18,767 nodes, 91 % have all eight
octants filled among them. Only the time depends on it, not the slots."""
HYPER_NEIGHBOURHOODS = 150
"""Neighbourhoods the covariance is fitted on (sampled nodes with their octant neighbours)."""
LENGTHS_M = tuple(float(v) for v in np.geomspace(0.25, 64.0, 9))
"""Covariance lengths tried, 0.25-64 m (a cell to a building), a factor 2 apart (then refined by half steps)."""
AMPLITUDES_M = tuple(float(v) for v in np.geomspace(0.01, 40.96, 7))
"""Covariance amplitudes (1 sigma) tried, 1 cm to 41 m, a factor 4 apart (then refined by half steps)."""
MIN_NODES = 2 * (8 * PER_OCTANT + 1)
"""Fewer nodes than this: the slopes stay scipy's (too few for the covariance to be fitted)."""
REMEMBERED_FITS = 16
"""Covariance fits `fitted_covariance` keeps, by their nodes' content (a few bytes each)."""
CHUNK = 250
"""Nodes whose systems are built and solved at once: a chunk's arrays (about 5 MB each) stay in the processor's
cache, where 2,000 nodes' (38 MB each) went out to memory between the steps that build them. The same result, a
quarter faster: on 12,522 nodes 1.37 -> 1.04 s (medians of three; 1,000: 1.23 s, 500: 1.13 s, 125: 1.02 s)."""


def _threads() -> int:
    """Threads the chunks of `gp_smoothed` run on: the cores this process may use. Each chunk is independent and numpy
    lets go of the interpreter in its array and linear-algebra loops, so they run side by side; every result is
    written to its own place, so the heights are the same to the bit on any count. (The covariance's trials run on
    one: `fit_covariance`.)"""
    return max(1, cores_available())


@dataclass(frozen=True)
class GpCovariance:
    """The Matern 5/2 covariance fitted to the nodes: length (m) and amplitude (1 sigma, m)."""

    length_m: float
    amplitude_m: float


def matern52(r_over_length: np.ndarray) -> np.ndarray:
    """The Matern 5/2 correlation at distances in units of the length."""
    a = math.sqrt(5.0) * np.asarray(r_over_length, dtype=float)
    return (1.0 + a + a * a / 3.0) * np.exp(-a)


def octant_neighbours(xy: np.ndarray, at: np.ndarray, tree: cKDTree | None = None,
                      per: int = PER_OCTANT) -> tuple[np.ndarray, np.ndarray]:
    """For each point of `at`, the indices into xy of up to `per` nearest nodes in each of the eight directions
    around it, plus a node at the point itself if there is one: (n, 8 per + 1) indices and a mask of the slots
    filled (an octant with fewer nodes leaves slots empty), from its CANDIDATES nearest nodes.

    The nearest FIRST_CANDIDATES are looked at first: a point whose eight octants each hold `per` of them has its
    answer there (the candidates come nearest first, so more of them could only add further ones), and only the
    others are asked for all CANDIDATES. The same slots, for a fraction of the k-d tree's work."""
    tree = cKDTree(xy) if tree is None else tree
    k_all = min(len(xy), CANDIDATES)
    k_first = min(k_all, FIRST_CANDIDATES)
    idx, keep, full = _octant_slots(xy, at, tree, k_first, per)
    again = ~full if k_first < k_all else np.zeros(len(at), dtype=bool)
    if again.any():
        idx[again], keep[again], _ = _octant_slots(xy, at[again], tree, k_all, per)
    return idx, keep


def _octant_slots(xy: np.ndarray, at: np.ndarray, tree: cKDTree, k0: int,
                  per: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`octant_neighbours` from the k0 nearest nodes, and which points have every octant filled among them."""
    _, idx0 = tree.query(at, k0)
    idx0 = np.asarray(idx0).reshape(len(at), k0)
    d = xy[idx0] - at[:, None, :]
    here = np.hypot(d[..., 0], d[..., 1]) < 1e-9
    octant = np.floor((np.arctan2(d[..., 1], d[..., 0]) + np.pi) / (np.pi / 4)).astype(np.int64) % 8
    octant[here] = 8
    # The rank of each candidate among its octant's: they come nearest first, so a stable sort by octant keeps
    # each octant's in order, and a candidate's rank is its place less its octant's first place.
    order = np.argsort(octant, axis=1, kind="stable")
    sorted_octant = np.take_along_axis(octant, order, axis=1)
    place = np.broadcast_to(np.arange(k0), octant.shape)
    first = np.maximum.accumulate(np.where(np.diff(sorted_octant, axis=1, prepend=-1) != 0, place, 0), axis=1)
    rank = np.empty_like(octant)
    np.put_along_axis(rank, order, place - first, axis=1)
    keep = np.where(octant == 8, rank < 1, rank < per)
    full = ((octant < 8) & keep).sum(axis=1) == 8 * per
    k = 8 * per + 1
    order = np.argsort(~keep, axis=1, kind="stable")[:, :k]
    return np.take_along_axis(idx0, order, axis=1), np.take_along_axis(keep, order, axis=1), full


@dataclass(frozen=True)
class _Neighbourhoods:
    """The nodes around each of n points (`octant_neighbours`): their slots, which are filled, their offsets from the
    point (n, k, 2; 0 in empty slots) and their distances from each other (n, k, k). What the kriging systems need
    besides the covariance, so a covariance fit makes it once for all the covariances it tries."""

    idx: np.ndarray
    valid: np.ndarray
    offsets_m: np.ndarray
    spacing_m: np.ndarray
    pairs: np.ndarray
    """(n, k, k) 1.0 where both slots are filled, else 0.0."""


def _neighbourhoods(xy: np.ndarray, at: np.ndarray, idx: np.ndarray, valid: np.ndarray) -> _Neighbourhoods:
    d = xy[idx] - at[:, None, :]
    d[~valid] = 0.0
    dist = np.subtract(d[:, :, None, 0], d[:, None, :, 0])
    np.square(dist, out=dist)
    dist += np.square(d[:, :, None, 1] - d[:, None, :, 1])
    np.sqrt(dist, out=dist)
    fv = valid.astype(float)
    return _Neighbourhoods(idx, valid, d, dist, fv[:, :, None] * fv[:, None, :])


def _correlation(nb: _Neighbourhoods, length_m: float, out: np.ndarray | None = None,
                 work: np.ndarray | None = None) -> np.ndarray:
    """(n, k, k) the Matern 5/2 correlation between the neighbourhoods' nodes at this length, 0 where a slot is
    empty: what the covariance's amplitude only scales, so a fit makes it once for every amplitude it tries. out: an
    array of that shape to write it into; work: (2, n, k, k) to compute in. A fit trying a dozen lengths reuses
    them: each fresh megabyte-sized array is memory the system maps page by page, which cost more than the
    arithmetic (4.6 -> 1.2 ms on 150 neighbourhoods). The same arithmetic in the same order as (1 + u + u^2 / 3)
    exp(-u) written out, so the same correlation to the bit."""
    work = np.empty((2, *nb.spacing_m.shape)) if work is None else work
    u, e = work[0], work[1]
    np.multiply(nb.spacing_m, math.sqrt(5.0) / length_m, out=u)  # u = sqrt(5) r / l
    np.negative(u, out=e)
    np.exp(e, out=e)
    poly = np.multiply(u, u, out=out)
    poly /= 3.0
    u += 1.0
    np.add(u, poly, out=poly)
    poly *= e
    poly *= nb.pairs
    return poly


HEIGHTS_CORNER = 1e300
"""The corner `_systems` puts on the diagonal below the heights' column, so that the bordered system is positive
definite whatever the heights (its Cholesky factor's last rows are then the forward substitution of the drift and the
heights, `restricted_loglik`); 1e300 less anything the heights can add to it stays positive, and its square root
squared stays finite."""


def _systems(nb: _Neighbourhoods, var: np.ndarray, cov: GpCovariance, corr: np.ndarray | None = None,
             out: np.ndarray | None = None, heights: np.ndarray | None = None) -> np.ndarray:
    """The universal-kriging systems of the neighbourhoods: (n, k + 3, k + 3) matrices, the covariance with the
    nodes' variances and a plane's drift (empty slots carry a huge variance and no covariance, so they take no
    weight). corr: `_correlation` at the covariance's length, when the caller has it. out: an array of that shape to
    write them into (every element is written), so a fit trying many covariances reuses one: a new megabyte-sized
    array each time is fresh memory the system maps page by page, which cost more than filling it. heights: (n, k)
    the nodes' heights (0 in empty slots), to border the covariance with them as well: (n, k + 4, k + 4), with
    HEIGHTS_CORNER on the diagonal below the drift's and the heights' columns in place of the drift's zeros."""
    idx, valid, d = nb.idx, nb.valid, nb.offsets_m
    n, k = idx.shape
    m = k + (3 if heights is None else 4)
    s2 = cov.amplitude_m**2
    corr = _correlation(nb, cov.length_m) if corr is None else corr
    a = np.empty((n, m, m)) if out is None else out
    np.multiply(corr, s2, out=a[:, :k, :k])
    diag = np.where(valid, var[idx], 1e6 * (1.0 + s2)) + 1e-10 * s2
    a.reshape(n, -1)[:, : k * (m + 1) : m + 1] += diag  # the diagonal of the covariance block, as a strided view
    a[:, :k, k] = 1.0
    a[:, :k, k + 1] = d[..., 0]
    a[:, :k, k + 2] = d[..., 1]
    if heights is not None:
        a[:, :k, k + 3] = heights
    a[:, k:, :k] = np.transpose(a[:, :k, k:], (0, 2, 1))
    a[:, k:, k:] = 0.0
    if heights is not None:
        a.reshape(n, -1)[:, k * (m + 1) :: m + 1] = HEIGHTS_CORNER
    return a


def restricted_loglik(nb: _Neighbourhoods, z: np.ndarray, var: np.ndarray, cov: GpCovariance,
                      corr: np.ndarray | None = None, scratch: np.ndarray | None = None) -> float:
    """Sum over the neighbourhoods (each around its nodes' centre) of the restricted log-likelihood of their node
    heights under the covariance with a plane's drift; -inf where a neighbourhood's covariance is not positive
    definite. corr: `_correlation` at the covariance's length, when the caller has it; scratch: `_systems`' out, (n,
    k + 4, k + 4).

    Through the covariance's Cholesky factor L: with Y = L^-1 [F z], F' C^-1 F = Yf' Yf, the drift's fit beta solves
    (Yf' Yf) beta = Yf' Yz, the quadratic form is |Yz - Yf beta|^2 and log det C = 2 sum log diag L. One factorisation
    of C bordered by [F z] (`_systems` with the heights) gives both L and, in its last rows, Y': the factorisation
    carries out the forward substitution as it goes. The same likelihood as the textbook formula (to 1e-12 relative
    on noisy nodes, 1e-8 on noise-free ones, whose covariances are the worst conditioned); a factorisation and a
    substitution of their own cost twice the CPU (docs/design-notes.md, "The covariance fit through its Cholesky
    factor", "The covariance fit, twice as fast")."""
    idx, valid = nb.idx, nb.valid
    k = idx.shape[1]
    a = _systems(nb, var, cov, corr, scratch, heights=np.where(valid, z[idx], 0.0))
    try:
        low = np.linalg.cholesky(a)
        y = np.transpose(low[:, k:, :k], (0, 2, 1))
        yf, yz = y[..., :3], y[..., 3]
        ftcif = np.einsum("nki,nkj->nij", yf, yf)
        low_f = np.linalg.cholesky(ftcif)  # not positive definite: nodes on one line, no plane to take out
        beta = np.linalg.solve(ftcif, np.einsum("nki,nk->ni", yf, yz)[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return -math.inf
    r = yz - np.einsum("nki,ni->nk", yf, beta)
    q = np.einsum("nk,nk->n", r, r)
    logdet = 2.0 * np.log(np.diagonal(low[:, :k, :k], axis1=1, axis2=2)).sum(axis=1)
    # The empty slots' huge variances add a constant to every covariance's determinant: leave them out.
    logdet = logdet - np.where(valid, 0.0, np.log(np.diagonal(a[:, :k, :k], axis1=1, axis2=2))).sum(axis=1)
    logdet_f = 2.0 * np.log(np.diagonal(low_f, axis1=1, axis2=2)).sum(axis=1)
    return float(-0.5 * np.sum(q + logdet + logdet_f))


def fit_covariance(xy: np.ndarray, z: np.ndarray, var: np.ndarray, seed: int = 0,
                   tree: cKDTree | None = None) -> GpCovariance:
    """The covariance (length, amplitude) that makes the node heights most likely (restricted maximum likelihood)
    over HYPER_NEIGHBOURHOODS sampled neighbourhoods: the grid LENGTHS_M x AMPLITUDES_M, then the half steps around
    its best. The sample is drawn with a fixed seed: the same nodes give the same surface.

    On one thread, length by length, in three arrays made once: the trials are small (150 systems of 37 unknowns),
    and on two threads they took 1.5 times the CPU for a tenth less time, where the report's second core is busy with
    the mount and the pose anyway (docs/design-notes.md, "The covariance fit, twice as fast")."""
    rng = np.random.default_rng(seed)
    centres = xy[rng.choice(len(z), size=min(HYPER_NEIGHBOURHOODS, len(z)), replace=False)]
    idx, valid = octant_neighbours(xy, centres, tree)
    centre = np.where(valid[..., None], xy[idx], 0.0).sum(axis=1) / np.maximum(valid.sum(axis=1), 1)[:, None]
    nb = _neighbourhoods(xy, centre, idx, valid)
    seen: dict[tuple[float, float], float] = {}
    n, k = nb.idx.shape
    corr, work, systems = np.empty((n, k, k)), np.empty((2, n, k, k)), np.empty((n, k + 4, k + 4))

    def most_likely(trials: list[tuple[float, float]]) -> tuple[float, float]:  # the first of the best, in order
        new = [t for t in dict.fromkeys(trials) if t not in seen]
        for length in sorted({la[0] for la in new}):
            _correlation(nb, length, corr, work)
            for la in (t for t in new if t[0] == length):
                seen[la] = restricted_loglik(nb, z, var, GpCovariance(*la), corr, systems)
        return max(trials, key=lambda la: seen[la])
    best = most_likely([(lv, av) for lv in LENGTHS_M for av in AMPLITUDES_M])
    step_l = math.sqrt(LENGTHS_M[1] / LENGTHS_M[0])
    step_a = math.sqrt(AMPLITUDES_M[1] / AMPLITUDES_M[0])
    best = most_likely([(best[0] * step_l**i, best[1] * step_a**j) for i in (-1, 0, 1) for j in (-1, 0, 1)])
    return GpCovariance(*best)


_fits: OrderedDict[bytes, GpCovariance] = OrderedDict()
_fits_lock = threading.Lock()


def fitted_covariance(xy: np.ndarray, z: np.ndarray, var: np.ndarray, tree: cKDTree | None = None) -> GpCovariance:
    """`fit_covariance` of these nodes, fitted once: the last REMEMBERED_FITS fits are kept by a digest of the nodes'
    positions, heights and variances, and the same nodes get the same covariance without the fit. The fit is a
    function of those alone (a fixed seed; the same to the bit on any thread count), so what is remembered is what
    would be computed. Why: the fit costs the same whatever the survey's size (0.1-0.2 s), and a process that reports
    one flight several ways surveys the same nodes again (a check with and without a correction that was not applied,
    options that do not touch the surface): over the ground station's, tools' and SITL's tests, 151 of 313 fits
    repeated one already made in the same process (docs/design-notes.md, "The covariance fit remembered by its
    nodes")."""
    arrays = [np.ascontiguousarray(a, dtype=float) for a in (xy, z, var)]
    digest = hashlib.blake2b(digest_size=20)
    for a in arrays:
        digest.update(repr(a.shape).encode())
        digest.update(a.tobytes())
    key = digest.digest()
    with _fits_lock:
        if key in _fits:
            _fits.move_to_end(key)
            return _fits[key]
    cov = fit_covariance(*arrays, tree=tree)
    with _fits_lock:
        _fits[key] = cov
        while len(_fits) > REMEMBERED_FITS:
            _fits.popitem(last=False)
    return cov


def forget_fits() -> None:
    """Forget every remembered fit. A benchmark that reports one flight again and again times a fresh report only
    when it forgets them before each run: remembered, the fit is a dictionary look-up (0.72 s against 0.93 s for the
    benchmark's default report), which no surveyor reporting a new flight gets."""
    with _fits_lock:
        _fits.clear()


def gp_smoothed(xy: np.ndarray, z: np.ndarray, var: np.ndarray, cov: GpCovariance,
                tree: cKDTree | None = None, only: np.ndarray | None = None) -> np.ndarray:
    """(n,) the kriging predictor's height at every node from its octant neighbours (itself among them, with its
    error variance): the node heights with their noise averaged out, and as they are where they have none. only:
    the indices of the nodes to predict (the others keep their heights), or None for all."""
    tree = cKDTree(xy) if tree is None else tree
    rows = np.arange(len(z)) if only is None else np.asarray(only, dtype=np.int64)
    out = np.array(z, dtype=float)
    s2, length = cov.amplitude_m**2, cov.length_m

    def chunk(lo: int) -> None:
        at = xy[rows[lo:lo + CHUNK]]
        idx, valid = octant_neighbours(xy, at, tree)
        nb = _neighbourhoods(xy, at, idx, valid)
        a = _systems(nb, var, cov)
        k = idx.shape[1]
        r = np.hypot(nb.offsets_m[..., 0], nb.offsets_m[..., 1])
        b = np.zeros((len(at), k + 3))
        b[:, :k] = np.where(valid, s2 * matern52(r / length), 0.0)
        b[:, k] = 1.0
        w = np.linalg.solve(a, b[..., None])[..., 0]
        out[rows[lo:lo + CHUNK]] = np.einsum("nk,nk->n", w[:, :k], np.where(valid, z[idx], 0.0))
    with ThreadPoolExecutor(max_workers=_threads()) as pool:
        list(pool.map(chunk, range(0, len(rows), CHUNK)))  # list(): a chunk's exception is raised here
    return out


def bridge_nodes(tri: Delaunay, reach_m: float) -> np.ndarray:
    """The indices of the nodes whose slopes the cubic carries beyond reach_m: the corners of every triangle with an
    edge longer than reach_m, and the nodes next to them (their heights set those corners' slopes). Elsewhere the
    cubic spans less than reach_m between nodes."""
    pts = np.asarray(tri.points, dtype=float)[tri.simplices]  # (m, 3, 2)
    longest = np.max(np.linalg.norm(pts - np.roll(pts, 1, axis=1), axis=2), axis=1)
    corner = np.zeros(len(tri.points), dtype=bool)
    corner[tri.simplices[longest > reach_m].ravel()] = True
    indptr, indices = tri.vertex_neighbor_vertices
    n = len(corner)
    beside = np.zeros(n, dtype=bool)
    if corner.any():
        owner = np.repeat(np.arange(n), np.diff(indptr))  # the node each neighbour entry belongs to
        beside[indices[corner[owner]]] = True
    return np.flatnonzero(corner | beside)


def node_slopes(tri: Delaunay, z: np.ndarray, se_m: np.ndarray, reach_m: float | None = None) -> np.ndarray | None:
    """The slopes (n, 2) at the triangulation's nodes: scipy's least-curvature slopes through the node heights the
    Gaussian process predicts (`gp_smoothed`), or None where the nodes cannot carry a fit (too few, or a height or
    error that is not a finite number, an error < 0): the caller keeps scipy's slopes through the heights then.
    reach_m: the process predicts only the heights of the `bridge_nodes` beyond it, the others are taken as they are
    (None when no triangle reaches that far: scipy's slopes)."""
    xy = np.asarray(tri.points, dtype=float)
    z = np.asarray(z, dtype=float)
    se = np.asarray(se_m, dtype=float)
    if len(z) < MIN_NODES or not (np.all(np.isfinite(se)) and np.all(se >= 0) and np.all(np.isfinite(z))):
        return None
    only = None if reach_m is None else bridge_nodes(tri, reach_m)
    if only is not None and not len(only):
        return None
    var = se * se
    try:
        tree = cKDTree(xy)  # one tree for the fit's neighbourhoods and the prediction's
        smoothed = gp_smoothed(xy, z, var, fitted_covariance(xy, z, var, tree), tree, only)
    except np.linalg.LinAlgError:  # a neighbourhood with no plane through it (its nodes on one line)
        return None
    if not np.all(np.isfinite(smoothed)):
        return None
    return CloughTocher2DInterpolator(tri, smoothed).grad[:, 0, :]
