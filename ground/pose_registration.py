"""The pose correction's registration on the pile seen at different times: on a slope a horizontal shift of a
stretch's points moves their height, so a sloped cell seen twice observes the along-track position the walls leave to
interpolation, and the heading (`register_from_crossings`), under a drift-smoothness prior (`bend_sigmas`); each kept
only when its gain beats fitting its knots to noise and the trajectory it gives is a drift (`registered`)."""

from __future__ import annotations

import math

import numpy as np
from scipy import sparse

from firmware_py.core.storage import Storage
from ground.crossing_cells import MAX_PILE_SLOPE, grid_cells, in_building, significant_gradients
from ground.group_stats import group_median, median_sd_m, rms, robust_rms
from ground.huber_lsq import huber_loss, irls_huber
from ground.plane_stretches import Beams
from ground.pose_decisions import is_drift
from ground.pose_knots import (
    BAND,
    MIN_CELL_POINTS,
    Component,
    PoseCorrectionOptions,
    corrected_points,
    knot_basis,
)


def bend_sigmas(b: Beams, knots: np.ndarray, k: np.ndarray, opts: PoseCorrectionOptions) -> np.ndarray:
    """(K, 4) the drift's second difference at each knot, one sigma (inf: none; z: none, a rangefinder's
    height steps over a pile). A velocity error that changes slowly (`drift_correlation_s`) makes a smooth
    position error: between knots dt apart its second difference is dt x the velocity error's change, from
    the error's own change (drift_rel x speed x sqrt(2 dt / tau)) and from the turns (the error is a fraction
    of the velocity, so it turns with it: drift_rel x |the logged velocity's change|), plus the hover walk's
    sqrt(2 dt); the heading's is its walk's."""
    n_knots = len(knots)
    out = np.full((n_knots, 4), np.inf)
    if n_knots < 3:
        return out
    dt = np.diff(knots)
    vel = np.zeros((n_knots - 1, 2))
    for c in range(2):
        pos = np.bincount(k, weights=b.vehicle_w[:, c], minlength=n_knots - 1)
        cnt = np.bincount(k, minlength=n_knots - 1)
        mean_t = np.bincount(k, weights=b.t_s, minlength=n_knots - 1) / np.maximum(cnt, 1)
        mean_p = pos / np.maximum(cnt, 1)
        vel[:, c] = np.gradient(mean_p, mean_t) if (cnt > 0).all() else 0.0
    speed = np.linalg.norm(vel, axis=1)
    h = 0.5 * (dt[:-1] + dt[1:])
    dv = np.linalg.norm(np.diff(vel, axis=0), axis=1)
    v_mid = 0.5 * (speed[:-1] + speed[1:])
    sig = (h * opts.horizontal_drift_rel * (dv + v_mid * np.sqrt(2.0 * h / opts.drift_correlation_s))
           + opts.hover_walk_m_per_sqrt_s * np.sqrt(2.0 * h))
    out[1:-1, 0] = out[1:-1, 1] = sig
    out[1:-1, 3] = opts.heading_walk_rad_per_sqrt_s * np.sqrt(2.0 * h)
    return out


def registered(b: Beams, x: np.ndarray, knots: np.ndarray, k: np.ndarray, f: np.ndarray, wall: np.ndarray,
               floor: np.ndarray, storage: Storage, cell_m: float, step: np.ndarray, noise: float, sensor_m: float,
               wall_info_total: np.ndarray, on: np.ndarray, z_free: bool, heading_held: bool,
               opts: PoseCorrectionOptions) -> tuple[np.ndarray, np.ndarray | None, list[str]]:
    """The position (and, with `opts.crossings_heading`, the heading) registered on the pile seen at different
    times (`register_from_crossings`), each kept only when its gain beats fitting its knots to noise.

    The walls' fit anchors each knot where they see it, with one point's information per knot (the walls'
    points within a knot interval share its systematic part: millimetres on the walls bought degrees of
    heading when each point counted, docs/pose_error.md): their information (wall_info_total, from the
    points `on`) divided by the points' weight on the knot."""
    n_knots = len(knots)
    kk, ff = k[on], f[on]
    weight = (np.bincount(kk, weights=(1 - ff) ** 2, minlength=n_knots)
              + np.bincount(kk + 1, weights=ff ** 2, minlength=n_knots))
    wall_info = wall_info_total / np.maximum(weight, 1.0)[:, None]
    elapsed = knots - knots[0]
    abs_sigma = np.tile([opts.max_position_error_m] * 3 + [opts.max_heading_error_rad], (n_knots, 1))
    abs_sigma[:, 3] = np.minimum(abs_sigma[:, 3], step[3] + opts.heading_bias_rad_s * elapsed
                                 + opts.heading_walk_rad_per_sqrt_s * np.sqrt(elapsed))
    bend = bend_sigmas(b, knots, k, opts)
    z_c = (Component.Z.value,) if z_free else ()
    xy = (Component.X.value, Component.Y.value)
    notes: list[str] = []

    def needed(n_extra: int) -> float:
        return n_extra + opts.n_significant * math.sqrt(2.0 * max(n_extra, 1))

    def register(start: np.ndarray, comps: tuple[int, ...], fixed: tuple[int, ...],
                 what: str) -> tuple[np.ndarray, np.ndarray, float, int] | None:
        """register_from_crossings; None (with a note) when what it gives is no drift (`is_drift`)."""
        out = register_from_crossings(b, start, x, knots, k, f, wall, floor, storage, cell_m, step, noise,
                                      sensor_m, wall_info, abs_sigma, comps, fixed, opts.max_position_error_m, bend)
        free = tuple(c for c in comps if c != Component.Z.value)  # a stage re-solves its fixed ones too
        if is_drift(out[0], start, step, free):
            return out
        notes.append(f"the {what} from the pile seen at different times was not used: the trajectory it gave "
                     "jumps more than the drift model allows")
        return None
    reg = register(x, z_c + xy, z_c, "position")
    if reg is None:
        return x, None, notes
    x_xy, info, gain, n_extra = reg
    if not (n_extra > 0 and gain > needed(n_extra)):
        return x, None, notes
    x_out, info_out = x_xy, info
    if opts.crossings_heading and heading_held:
        reg_h = register(x_xy, z_c + xy + (Component.HEADING.value,), z_c + xy, "heading")
        x_h, info_h, gain_h, n_h = reg_h if reg_h is not None else (x_xy, info, 0.0, 0)
        if n_h > 0 and gain_h > needed(n_h):
            x_out, info_out = x_h, info_h
            notes.append(f"the heading from the pile seen at different times ({math.degrees(rms(x_h[:, 3])):.2f} deg "
                         "RMS)")
        elif reg_h is not None:  # said, so a surveyor knows an indoor heading's drift is still in the volume
            why = (f"does not show it off: fitting it gains {gain_h:.0f}, where fitting {n_h} knots to noise would "
                   f"gain up to {needed(n_h):.0f}" if n_h > 0 else "constrains no knot of it")
            notes.append(f"the heading was left as logged: the pile seen at different times {why}")
    return x_out, info_out, notes


def register_from_crossings(b: Beams, x: np.ndarray, x_wall: np.ndarray, knots: np.ndarray, k: np.ndarray,
                            f: np.ndarray, wall: np.ndarray, floor: np.ndarray, storage: Storage, cell_m: float,
                            step: np.ndarray, noise_m: float, sensor_m: float, wall_info: np.ndarray,
                            abs_sigma: np.ndarray,
                            comps: tuple[int, ...], fixed: tuple[int, ...], max_error_m: float,
                            bend: np.ndarray | None = None, n_sigma: float = 3.0,
                            rounds: int = 3) -> tuple[np.ndarray, np.ndarray, float, int]:
    """The pile seen at different times registered in position (and heading) too, not only in height.

    Each knot interval's points in a cell give one height at the cell's centre (`vertical_from_crossings`);
    on a slope a horizontal shift s of that interval's points changes it by g . s (g: the cell's gradient,
    fitted from all its points), and a heading change dpsi by g . J v dpsi (v: the interval's mean beam vector
    there, horizontal; J: a quarter turn): a heading error turns the sweep about the vehicle, moving a point
    at lateral distance D by D dpsi along the track, which the walls beside the track do not see and the
    pile's slope along the track does. So the along-track position between turns, which the walls leave to
    interpolation, is observed wherever a cell on a slope is seen twice. Linearised about x (K, 4), solved
    for the components `comps` (Component values) with the cells' heights, robustly (Huber, IRLS), with the
    knots' random-walk prior (step (4,)), the walls' information on each knot (wall_info (K, 4): the wall fit
    x_wall is kept where the walls see it) and an absolute prior (abs_sigma (K, 4)); `rounds` re-fits of the
    cells' gradients with the correction so far.

    Returns the correction (K, 4), the crossings' information on each knot (K, 4; 1/m^2, 1/rad^2), the
    Huber gain of the components `comps` not in `fixed` over holding them at x's values (in the residuals'
    own spread: a chi-square-like gain) and the number of knot values the crossings constrain among them."""
    n_knots = len(knots)
    comps = tuple(comps)
    nc = len(comps)
    x = x.copy()
    x_start = x.copy()
    info = np.zeros((n_knots, 4))
    gain, n_extra = 0.0, 0
    for rnd in range(rounds):
        p, vr = corrected_points(b, x, k, f)
        inside = in_building(p, wall, storage, max_error_m)
        nx, ny, cid = grid_cells(p, storage, cell_m)
        flat, gx, gy = significant_gradients(p, cid, nx * ny, cell_m, ny, inside, n_sigma)
        z_flat = p[:, 2] - flat
        key_all = k * (nx * ny) + cid
        key, med, mad, tm, cnt = group_median(key_all[inside], z_flat[inside], b.t_s[inside])
        gi = np.searchsorted(key, key_all[inside])
        vx = np.bincount(gi, weights=vr[inside, 0], minlength=len(key)) / cnt
        vy = np.bincount(gi, weights=vr[inside, 1], minlength=len(key)) / cnt
        fl = np.bincount(gi, weights=floor[inside].astype(float), minlength=len(key))
        is_floor = fl * 2 >= cnt
        # a surface steeper than a granular pile's angle of repose is a wall or a pile's toe against one (a
        # cell across a step): not linear in a shift, it is left out
        # nor is a cell whose points in one interval scatter about its plane beyond the sensor's noise: a step
        # (a block's edge, a wall's foot) is not a plane either
        # and a cell on the building's edge holds a wall's foot, a step, whatever the wall's points assigned
        cx_i, cy_i = (key % (nx * ny)) // ny, (key % (nx * ny)) % ny
        edge = (cx_i == 0) | (cx_i == nx - 1) | (cy_i == 0) | (cy_i == ny - 1)
        keep = ((cnt >= MIN_CELL_POINTS) & (np.hypot(gx, gy)[key % (nx * ny)] <= MAX_PILE_SLOPE)
                & (mad <= BAND * max(sensor_m, noise_m)) & ~edge)
        key, med, mad, tm, cnt, vx, vy, is_floor = (a[keep] for a in (key, med, mad, tm, cnt, vx, vy, is_floor))
        cell = key % (nx * ny)
        seen, inv, times_seen = np.unique(cell, return_inverse=True, return_counts=True)
        floor_cells = pinned_to_floor(seen, inv, is_floor, gx, gy)
        use = (times_seen[inv] >= 2) | floor_cells[inv]
        key, med, mad, tm, cnt, vx, vy, cell, inv = (a[use] for a in (key, med, mad, tm, cnt, vx, vy, cell, inv))
        if len(key) == 0:
            return x_start, info, 0.0, 0
        uniq_cells, cell_idx = np.unique(inv, return_inverse=True)
        n_cells = len(uniq_cells)
        fc = np.flatnonzero(floor_cells[uniq_cells])
        g_x, g_y = gx[cell], gy[cell]
        # d(height at the cell's centre)/d(component): z 1, x -gx, y -gy, heading -g . J v
        coef = {Component.Z.value: np.ones(len(key)), Component.X.value: -g_x, Component.Y.value: -g_y,
                Component.HEADING.value: -(g_x * -vy + g_y * vx)}
        rows_s = median_sd_m(mad, cnt, noise_m)
        kk, ff = knot_basis(tm, knots)
        m_obs, m_floor = len(med), len(fc)
        n_par = nc * n_knots + n_cells
        r_i, c_i, d_i = [], [], []
        obs = np.arange(m_obs)
        for ci, c in enumerate(comps):
            r_i += [obs, obs]
            c_i += [ci * n_knots + kk, ci * n_knots + kk + 1]
            d_i += [coef[c] * (1 - ff) / rows_s, coef[c] * ff / rows_s]
        r_i += [obs, m_obs + np.arange(m_floor)]
        c_i += [nc * n_knots + cell_idx, nc * n_knots + fc]
        d_i += [-1.0 / rows_s, np.full(m_floor, 1.0 / noise_m)]
        a_obs = sparse.csr_matrix((np.concatenate(d_i), (np.concatenate(r_i), np.concatenate(c_i))),
                                  shape=(m_obs + m_floor, n_par))
        # the cells' heights relative to the current points: delta solves a_obs delta = b_obs
        b_obs = np.concatenate([-med / rows_s, np.zeros(m_floor)])
        # priors on the totals x + delta: steps, the walls' fit where they see it, absolute
        pr, pc, pd, pb = [], [], [], []
        r = 0
        for ci, c in enumerate(comps):
            for i in range(n_knots - 1):
                pr += [r, r]
                pc += [ci * n_knots + i, ci * n_knots + i + 1]
                pd += [-1.0 / step[c], 1.0 / step[c]]
                pb.append(-(x[i + 1, c] - x[i, c]) / step[c])
                r += 1
            if bend is not None and np.isfinite(bend[:, c]).any():
                for i in range(1, n_knots - 1):
                    if not np.isfinite(bend[i, c]):
                        continue
                    pr += [r, r, r]
                    pc += [ci * n_knots + i - 1, ci * n_knots + i, ci * n_knots + i + 1]
                    pd += [1.0 / bend[i, c], -2.0 / bend[i, c], 1.0 / bend[i, c]]
                    pb.append(-(x[i - 1, c] - 2.0 * x[i, c] + x[i + 1, c]) / bend[i, c])
                    r += 1
            for i in range(n_knots):
                w = math.sqrt(wall_info[i, c]) if c != Component.Z.value else 0.0
                if w > 0:
                    pr.append(r)
                    pc.append(ci * n_knots + i)
                    pd.append(w)
                    pb.append(-w * (x[i, c] - x_wall[i, c]))
                    r += 1
                pr.append(r)
                pc.append(ci * n_knots + i)
                pd.append(1.0 / abs_sigma[i, c])
                pb.append(-x[i, c] / abs_sigma[i, c])
                r += 1
        for i in range(n_cells):
            pr.append(r)
            pc.append(nc * n_knots + i)
            pd.append(1.0 / storage.height_m)
            pb.append(0.0)
            r += 1
        a_pr = sparse.csr_matrix((pd, (pr, pc)), shape=(r, n_par))
        # The heights scatter about the model by more than their points' spread says (a cell's plane is an
        # approximation, the footprints differ between passes): the rows in their residuals' own spread, so
        # the data weigh against the prior as much as they are worth.
        a = sparse.vstack([a_obs, a_pr], format="csr")
        rhs = np.concatenate([b_obs, np.asarray(pb)])
        sol = irls_huber(a, rhs)
        spread = max(1.0, robust_rms(a_obs @ sol - b_obs))
        if spread > 1.0:
            a_obs, b_obs = a_obs / spread, b_obs / spread
            a = sparse.vstack([a_obs, a_pr], format="csr")
            rhs = np.concatenate([b_obs, np.asarray(pb)])
            sol = irls_huber(a, rhs)
        delta = sol[:nc * n_knots].reshape(nc, n_knots).T
        a_k = a_obs[:, :nc * n_knots]
        col_info = np.asarray(a_k.multiply(a_k).sum(axis=0)).ravel().reshape(nc, n_knots).T
        if rnd == rounds - 1:
            # the gain of the components not fixed: the same rows with them held at x_start's values
            spread = 1.0  # the rows are in their own spread already
            free = [ci for ci, c in enumerate(comps) if c not in fixed]
            if free:
                held_cols = np.concatenate([np.arange(ci * n_knots, (ci + 1) * n_knots) for ci in free])
                rest = np.setdiff1d(np.arange(n_par), held_cols)
                held_val = np.concatenate([(x_start[:, comps[ci]] - x[:, comps[ci]]) for ci in free])
                rhs_h = rhs - a[:, held_cols] @ held_val
                sol_h = irls_huber(a[:, rest], rhs_h)
                r_held = a_obs[:, rest] @ sol_h - (b_obs - a_obs[:, held_cols] @ held_val)
                r_full = a_obs @ sol - b_obs
                gain = 2.0 * float(np.sum(huber_loss(r_held / spread)) - np.sum(huber_loss(r_full / spread)))
                n_extra = int(sum(np.count_nonzero(col_info[:, ci] * step[comps[ci]] ** 2 / spread ** 2 >= 1.0)
                                  for ci in free))
            for ci, c in enumerate(comps):
                info[:, c] = col_info[:, ci] / spread ** 2
        for ci, c in enumerate(comps):
            x[:, c] += delta[:, ci]
    if m_floor == 0 and Component.Z.value in comps:
        # No floor cell: the height's level is not observed (one constant added to every knot and cell fits the
        # same), and the cells' weak pull towards the floor set it: thousands of cells against a few dozen knots put
        # the pile's mean height into the vehicle's (1.0-2.0 m: pile 2, Ve 44-52 %). It goes back where the height
        # solved before put it. (At the end, not in each round: the rounds stay as they were, and holding the level
        # in them changed which registration was kept on a `flow` flight over pile 1, Ve 0.23 -> 7.1 %.)
        x[:, Component.Z.value] += float(np.mean(x_start[:, Component.Z.value]) - np.mean(x[:, Component.Z.value]))
    return x, info, gain, n_extra


def pinned_to_floor(cells: np.ndarray, inv: np.ndarray, is_floor: np.ndarray, gx: np.ndarray,
                    gy: np.ndarray) -> np.ndarray:
    """Per distinct cell (`cells`, the grid's cell ids; `inv`: each row's index into them), whether the registration
    holds its height at the floor's 0: a knot interval saw mostly floor points in it (`is_floor`, per row), and the
    cell is flat (no significant gradient: gx, gy per grid cell, `significant_gradients`).

    A pile's toe holds both: the floor beside it and the flank's lowest decimetres, which the floor's band takes for
    the floor. Pinned to 0 with its fitted slope, such a cell had every pass seeing it pay for the kink with a shift
    up the slope, and the pile came out pulled in: on the true pose of 38 flights over our own cone and ridge, the
    forced registration moved their volume by -0.15 % on average (up to -0.8 %), by -0.05 % once sloped cells were
    left free (docs/design-notes.md). Free, a sloped cell counts as any cell seen twice: its passes must agree with
    one another, not with a floor."""
    pinned = np.zeros(len(cells), dtype=bool)
    pinned[inv[is_floor]] = True
    return pinned & (np.hypot(gx, gy)[cells] == 0)
