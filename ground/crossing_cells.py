"""The pile seen at different times, in cells: the points the crossings compare (inside the building, not a wall's),
each point's cell on a grid, and each cell's fitted slope. The slope is taken out of a cell's heights so that two
passes hitting a sloped cell in different places agree, and where it is significant it is what a horizontal shift is
registered on. The height (`ground.pose_height`) and the registration (`ground.pose_registration`) compare the pile in
these cells."""

from __future__ import annotations

import math

import numpy as np

from firmware_py.core.storage import Storage

MIN_PILE_SLOPE = 0.05
"""The gentlest surface slope a shift is registered on (3 deg): steeper than a floor's fall (drainage: up to 2 %) with
margin; below it a centimetre of height error (a drifting height within a pass, a range quantum) is a metre of shift."""
MAX_PILE_SLOPE = 1.0
"""The steepest surface slope registered on (tan 45 deg: above any granular material's angle of repose, ~30-40 deg)."""


def flattened(p: np.ndarray, wall: np.ndarray, storage: Storage, cell_m: float, max_error_m: float,
              slope_z: np.ndarray | None = None) -> tuple[np.ndarray, int, int, np.ndarray, np.ndarray]:
    """What the crossings compare: the points they use (`in_building`), the cells (nx, ny, each point's) and each
    point's height with its cell's slope taken out. The slope is fitted from all the cell's points, every time
    together (with heights slope_z, default p's own): the height a knot interval gives is then at the cell's
    centre, so two passes that hit a sloped cell in different places still agree. Returns (inside, nx, ny, cid,
    z_flat)."""
    inside = in_building(p, wall, storage, max_error_m)
    nx, ny, cid = grid_cells(p, storage, cell_m)
    seen = p if slope_z is None else np.column_stack([p[:, :2], slope_z])
    return inside, nx, ny, cid, p[:, 2] - cell_slopes(seen, cid, nx * ny, cell_m, ny, inside)


def up_noise_m(to_point_w: np.ndarray, angle_sigma_rad: float, n_sigma: float = 3.0) -> np.ndarray:
    """How far above the vehicle a level beam's point may lie by its pointing noise alone: n_sigma of the header's
    pointing error (1 sigma) at each point's range. A position error moves the vehicle and its points together, so it
    is not in it."""
    return n_sigma * angle_sigma_rad * np.linalg.norm(np.asarray(to_point_w, dtype=float), axis=1)


def not_the_pile(wall: np.ndarray, to_point_w: np.ndarray, angle_sigma_rad: float = 0.0,
                 n_sigma: float = 3.0) -> np.ndarray:
    """The points the crossings leave out as no part of the pile's surface: the walls' (`wall`, as their fit assigned
    them) and every point a beam pointing level or upward hit (to_point_w (n, 3): from the vehicle to the point, in
    W), up by more than its own pointing noise (`up_noise_m` with the header's angle_sigma_rad), under which a level
    beam passes for one pointing up. The vehicle flies over the pile, so what a beam finds at or above the vehicle's
    height is a wall or the roof. The walls' fit misses such points where the pose is metres off: a sweep wider than
    a half turn (a servo 5 % over its calibration swings 94.5 deg to each side) reaches the walls above the vehicle,
    and in the cells beside a wall those points passed for a pile 2 m higher than another pass saw it, which made the
    registration jump and be refused (docs/design-notes.md, "Beams pointing up are no pile")."""
    up_m = up_noise_m(to_point_w, angle_sigma_rad, n_sigma)
    return np.asarray(wall, dtype=bool) | (np.asarray(to_point_w, dtype=float)[:, 2] >= up_m)


def in_building(p: np.ndarray, wall: np.ndarray, storage: Storage, max_error_m: float) -> np.ndarray:
    """The points the crossings use: inside the building's walls and under its roof, not a wall's, and no deeper
    below the floor than the largest position error looked for (max_error_m)."""
    return (~wall & (p[:, 0] > 0) & (p[:, 0] < storage.length_m) & (p[:, 1] > 0) & (p[:, 1] < storage.width_m)
            & (p[:, 2] > -max_error_m) & (p[:, 2] < storage.height_m))


def grid_cells(p: np.ndarray, storage: Storage, cell_m: float) -> tuple[int, int, np.ndarray]:
    nx = max(1, math.ceil(storage.length_m / cell_m))
    ny = max(1, math.ceil(storage.width_m / cell_m))
    cid = (np.clip((p[:, 0] / cell_m).astype(np.int64), 0, nx - 1) * ny
           + np.clip((p[:, 1] / cell_m).astype(np.int64), 0, ny - 1))
    return nx, ny, cid


def cell_slopes(p: np.ndarray, cid: np.ndarray, n_cells: int, cell_m: float, ny: int,
                use: np.ndarray) -> np.ndarray:
    """Per point, its cell's least-squares plane's height above the cell's centre at the point (0 where the
    cell's points do not span both directions)."""
    return cell_gradients(p, cid, n_cells, cell_m, ny, use)[0]


def cell_gradients(p: np.ndarray, cid: np.ndarray, n_cells: int, cell_m: float, ny: int,
                   use: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`cell_slopes`, and each cell's gradient (gx, gy) (n_cells,) each (0 where not fitted)."""
    cx = (cid // ny + 0.5) * cell_m
    cy = (cid % ny + 0.5) * cell_m
    dx, dy, z = p[:, 0] - cx, p[:, 1] - cy, p[:, 2]
    w = use.astype(float)

    def s(v: np.ndarray) -> np.ndarray:
        return np.bincount(cid, weights=v * w, minlength=n_cells)
    n, sx, sy, sz = s(np.ones(len(p))), s(dx), s(dy), s(z)
    sxx, sxy, syy, sxz, syz = s(dx * dx), s(dx * dy), s(dy * dy), s(dx * z), s(dy * z)
    safe = np.maximum(n, 1.0)
    # centred moments
    cxx, cxy, cyy = sxx - sx * sx / safe, sxy - sx * sy / safe, syy - sy * sy / safe
    cxz, cyz = sxz - sx * sz / safe, syz - sy * sz / safe
    det = cxx * cyy - cxy * cxy
    ok = (n >= 6) & (det > 1e-3 * np.maximum(cxx * cyy, 1e-12))
    gx = np.where(ok, (cyy * cxz - cxy * cyz) / np.where(ok, det, 1.0), 0.0)
    gy = np.where(ok, (cxx * cyz - cxy * cxz) / np.where(ok, det, 1.0), 0.0)
    return gx[cid] * dx + gy[cid] * dy, gx, gy


def significant_gradients(p: np.ndarray, cid: np.ndarray, n_cells: int, cell_m: float, ny: int, use: np.ndarray,
                          n_sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`cell_gradients`, with the gradient set to 0 where the plane does not explain more than n_sigma^2 (per
    degree of freedom) of its points' scatter: a flat cell's fitted slope is its noise's, and a shift would be
    bought from it."""
    flat, gx, gy = cell_gradients(p, cid, n_cells, cell_m, ny, use)
    w = use.astype(float)
    cx = (cid // ny + 0.5) * cell_m
    cy = (cid % ny + 0.5) * cell_m
    dx, dy = p[:, 0] - cx, p[:, 1] - cy
    n = np.bincount(cid, weights=w, minlength=n_cells)
    res = p[:, 2] - flat
    mean_res = np.bincount(cid, weights=res * w, minlength=n_cells) / np.maximum(n, 1.0)
    ssr = np.bincount(cid, weights=(res - mean_res[cid]) ** 2 * w, minlength=n_cells)
    s2 = ssr / np.maximum(n - 3.0, 1.0)
    mx = np.bincount(cid, weights=dx * w, minlength=n_cells) / np.maximum(n, 1.0)
    my = np.bincount(cid, weights=dy * w, minlength=n_cells) / np.maximum(n, 1.0)
    ex, ey = dx - mx[cid], dy - my[cid]
    # the part of the scatter the slope explains: sum (g . (p - mean))^2
    explained = np.bincount(cid, weights=(gx[cid] * ex + gy[cid] * ey) ** 2 * w, minlength=n_cells)
    sig = (explained > 2.0 * n_sigma ** 2 * np.maximum(s2, 1e-12)) & (np.hypot(gx, gy) >= MIN_PILE_SLOPE)
    # and only where the slope continues up or down it: one cell across a block's edge, at a 0.93 slope, was a
    # registration's only sloped cell and moved a synthetic flight's along-track position by a metre, or not,
    # as a 2 % change of the cell size put the grid's cut across the edge
    sig &= slope_continues(sig, gx, gy, n_cells, ny)
    gx, gy = np.where(sig, gx, 0.0), np.where(sig, gy, 0.0)
    return gx[cid] * dx + gy[cid] * dy, gx, gy


def slope_continues(sloped: np.ndarray, gx: np.ndarray, gy: np.ndarray, n_cells: int, ny: int) -> np.ndarray:
    """Per cell (x-major, ny cells a column): whether its slope continues into a neighbour up or down it (the
    neighbour the gradient points to, or the one opposite, is sloped too, the same way). A pile's flank spans
    several cells; a step (a block's edge, a wall's foot) has flat cells on both sides, and the slope fitted
    across it is wherever the grid happened to cut it."""
    nx = n_cells // ny
    ix, iy = np.divmod(np.arange(n_cells), ny)
    g = np.hypot(gx, gy)
    sx = np.rint(np.divide(gx, g, out=np.zeros_like(gx), where=g > 0)).astype(np.int64)
    sy = np.rint(np.divide(gy, g, out=np.zeros_like(gy), where=g > 0)).astype(np.int64)
    out = np.zeros(n_cells, dtype=bool)
    for sign in (1, -1):
        jx, jy = ix + sign * sx, iy + sign * sy
        inside = (jx >= 0) & (jx < nx) & (jy >= 0) & (jy < ny) & ((sx != 0) | (sy != 0))
        j = np.where(inside, jx * ny + jy, 0)
        out |= inside & sloped[j] & (gx * gx[j] + gy * gy[j] > 0)
    return out
