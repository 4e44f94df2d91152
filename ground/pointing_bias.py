"""Where a pointing error places every point: behind the surface it hit, along its beam.

A beam turned by a pointing error delta (the servo's angle, the attitude) from the direction it is placed along meets
the surface at another range. For a locally flat surface with unit normal n, a beam d and the direction u the error
turns it in (across the beam, in the plane the servo sweeps it through), the range it comes back with is

    r(delta) = r / (1 + delta t - delta^2 / 2),  t = (u . n) / (d . n),

and the point is placed at that range along d. Its mean over a zero-mean delta of sigma is r (1 + sigma^2 (t^2 + 1/2)):
every point lies r sigma^2 (t^2 + 1/2) behind the surface on average, never in front, most where the beam grazes (t
large). Under Appendix A's one degree at 20 m that is 3 mm square on and 9 mm at 45 degrees, and it reads the surface
low: the paper's piles 0.1-0.3 % under (measured: docs/design-notes.md, "Four biases of the noisy surface"). Smoothing
cannot take it off, since every point carries it with one sign; knowing sigma from the log header and the surface's
normal from a first fit, `along_beam_bias_m` gives it per point, and the points are moved back along their beams by it
before the surface is fitted again.

The expansion holds while the beam meets the surface at an angle (alpha, t = cot alpha) well above sigma: within 2 %
at alpha = 10 sigma (measured by sampling), where t is capped. It is capped at ten degrees whatever sigma is, too:
the normal comes from the fitted cells, good to a few degrees, and below ten degrees of grazing a few degrees change t
by tens of percent.

Not yet modelled, so the correction is an option: the expansion assumes the surface goes on whichever way the error
turns the beam. At grazing incidence near a wall or a pile's foot a beam turned away from the surface meets something
else, so the hits that remain are the short ones, placed in front of the surface: measured +48 mm on a small
building's floor at 70-80 degrees from the vertical, where the expansion says -28 mm (docs/design-notes.md).
"""

from __future__ import annotations

import math

import numpy as np

from ground.smoothing import cell_index

MIN_GRAZING_RAD = math.radians(10.0)
"""The shallowest angle between beam and surface whose t is taken (module docstring: the fitted normal's accuracy)."""
EXPANSION_SIGMAS = 10.0
"""... and no shallower than this many pointing sigmas: the second-order expansion is within 2 % there."""


def sweep_directions(dirs_w: np.ndarray) -> np.ndarray:
    """(N, 3) per beam, the unit direction its pointing error turns it in: across the beam, in the plane the servo
    sweeps it through, taken from its neighbours in sample order (the sweep turns the beam from one sample to the
    next); zero where they do not say (a lone sample, a beam that did not turn)."""
    d = np.asarray(dirs_w, dtype=float)
    if len(d) < 2:
        return np.zeros_like(d)
    step = np.empty_like(d)
    step[1:-1] = d[2:] - d[:-2]
    step[0], step[-1] = d[1] - d[0], d[-1] - d[-2]
    step -= np.sum(step * d, axis=1, keepdims=True) * d  # across the beam only
    norm = np.linalg.norm(step, axis=1, keepdims=True)
    return np.where(norm > 1e-9, step / np.maximum(norm, 1e-300), 0.0)


def max_t(angle_sigma_rad: float) -> float:
    """The largest t = cot(alpha) taken (module docstring)."""
    return 1.0 / math.tan(max(MIN_GRAZING_RAD, EXPANSION_SIGMAS * angle_sigma_rad))


def along_beam_bias_m(range_m: np.ndarray, dirs_w: np.ndarray, across_w: np.ndarray, normals_w: np.ndarray,
                      angle_sigma_rad: float) -> np.ndarray:
    """Per point, how far behind the surface along its beam a pointing error of angle_sigma_rad places it on average:
    r sigma^2 (t^2 + 1/2) (module docstring). across_w: `sweep_directions`; normals_w: the surface's unit normals at
    the points, NaN where unknown (t is then 0: the bias of a beam square on, the least there is)."""
    if not angle_sigma_rad > 0:
        return np.zeros(len(range_m))
    dn = np.abs(np.sum(dirs_w * normals_w, axis=1))
    un = np.abs(np.sum(across_w * normals_w, axis=1))
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.minimum(un / dn, max_t(angle_sigma_rad))
    t = np.where(np.isfinite(t), t, 0.0)
    return np.asarray(range_m, dtype=float) * angle_sigma_rad**2 * (t * t + 0.5)


def grid_normals(points_w: np.ndarray, heights: np.ndarray, cell_xy_m: tuple[float, float]) -> np.ndarray:
    """(N, 3) the unit upward normal of a height grid (nx, ny) over the floor [0, nx cx] x [0, ny cy] at each point's
    cell, from its central differences; NaN where the cell or a neighbour it needs has no height."""
    h = np.asarray(heights, dtype=float)
    nx, ny = h.shape
    cx, cy = cell_xy_m
    gx = np.gradient(h, cx, axis=0) if nx > 1 else np.zeros_like(h)
    gy = np.gradient(h, cy, axis=1) if ny > 1 else np.zeros_like(h)
    flat = cell_index(points_w, (nx, ny), cell_xy_m)
    n = np.column_stack([-gx.ravel()[flat], -gy.ravel()[flat], np.ones(len(flat))])
    return n / np.linalg.norm(n, axis=1, keepdims=True)
