"""Where the material meets the walls: evidence from the sweeps that reached a wall, for the unseen fill.

The walls are known planes, and a sweep that reaches a wall says where the wall is visible. Take two
consecutive beams of one sweep, one on a wall at height z_w and the next one short of it, on material
or the floor. The wall beam passed over everything on its way, so the material at the wall there is no
higher than z_w. The other beam was stopped before the wall; had it gone on, it would have met the
wall at z' below z_w. For material leaning on the wall (rising, or level, towards it) the surface
between that hit and the wall stays above the beam, so the material meets the wall no lower than z'.
The contact line lies in [z', z_w]: the *wall contact*, estimated by z_w (the lowest wall hit marks
it). A beam stopped by the floor beside the wall gives z' below the floor: the wall is seen down to
(near) its foot, no material there (estimate 0). Material leaning on the wall rises or is level towards
it, so its last hit short of the wall is no higher than the wall seen above it: a last hit above that
(a pile's crest metres from the wall, the wall seen low behind it, as on the paper's pile 1) marks no
contact, since the ground falls away unseen between them.

These are the surface's only evidence at the wall's foot and in the corners, exactly where a fill
that copies the nearest seen cell has none (docs/design-notes.md, "Wall-contact evidence for the
unseen fill"). The `wall-contact` empty-cell policy fits the surface through them as nodes at the walls'
feet (`contact_nodes`); `contact_fill` (pinned in the unseen wall cells instead) is what docs/unseen.md
compared it with.

Tolerances come from the log header's sensor model (`SensorErrorModel`): each end of the interval is
widened by k vertical sigmas (range along the beam, pointing across it, position, range quantum), k =
`structure_n_sigma` of the cloud's size, as the wall tolerance is; the top also by the wall tolerance
times MAX_SLOPE, since the lowest "wall" hit may be material that close to the wall. A contact needs
the material seen by two consecutive beams, so a single wall return that escaped the structure mask
(noise) makes none.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from firmware_py.core.storage import Storage
from ground.pointcloud import Cloud, SensorErrorModel, plane_tolerances_m, structure_n_sigma
from ground.smoothing import vertical_sigma_m
from ground.unseen import MAX_SLOPE, Extension, bounded_fill

CONTACT_REST = "nearest"
"""The empty-cell policy for what the surface through the contacts still leaves empty (docs/unseen.md:
`nodes-nearest` against `nodes-bounded`)."""
WALL_LIKE_SIGMAS = 2.0
"""For the estimate only (not the bounds): a "wall" hit further inside the wall plane than this many of its
own sigmas along the normal is taken as material close to the wall (one-sided, 2 % of true wall hits), and
the contact is looked for further up the sweep, at its first hit that lies on the plane."""
MAX_WALK = 64
"""Most hits walked up a sweep from the lowest wall hit looking for the first one on the plane."""
MAX_GAP_SAMPLES = 1.5
"""Two usable samples are sweep neighbours when their times differ by at most this many sample periods
(the median spacing): a dropped sample between them breaks the pair (the beams are no longer adjacent)."""


@dataclass(frozen=True)
class WallContacts:
    """Where material (or the bare floor) meets a wall, one row per sweep transition wall -> material.

    Attributes:
        xy_m: (n, 2) the contact's place on the wall's foot line (on the wall plane).
        height_m: (n,) the estimate: the lowest wall hit's height, or the floor (0) where the beam short of
            the wall hit the floor (the floor runs to the wall: a bare foot).
        low_m, high_m: (n,) the material's height at the wall there lies in [low, high] (noise included).
        wall: (n,) which wall: 0 x = 0, 1 x = length, 2 y = 0, 3 y = width.
        leans_as_measured: (n,) the material's last hit short of the wall is no higher than the wall hit above it
            as measured, without the leaning test's noise allowance (None: all are taken to be).
    """

    xy_m: np.ndarray
    height_m: np.ndarray
    low_m: np.ndarray
    high_m: np.ndarray
    wall: np.ndarray
    leans_as_measured: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.low_m)

    def measured_leaning(self) -> WallContacts:
        """The contacts whose material leans on the wall as measured (`leans_as_measured`). The leaning test's noise
        allowance lets a pair of beams across a crest metres from the wall pass under a large pointing error (1 deg
        at 30 m: metres), so these are the contacts to take a fitted cell away on (`ground.wall_strip`); the fill
        keeps them all, since a missed contact costs it evidence along a whole wall (docs/design-notes.md, "The
        wall strip")."""
        if self.leans_as_measured is None:
            return self
        k = np.asarray(self.leans_as_measured, dtype=bool)
        return WallContacts(self.xy_m[k], self.height_m[k], self.low_m[k], self.high_m[k], self.wall[k], k[k])


def _walls(storage: Storage) -> tuple[tuple[int, float], ...]:
    """(normal axis, plane position) of walls 0-3."""
    return ((0, 0.0), (0, storage.length_m), (1, 0.0), (1, storage.width_m))


def wall_index(points_w: np.ndarray, tol_xyz: np.ndarray, storage: Storage) -> np.ndarray:
    """Each point's wall (0-3, `WallContacts.wall`): the wall it lies fewest tolerances from, -1 when it is
    further than its tolerance from every wall."""
    dist = np.column_stack([np.abs(points_w[:, axis] - pos) / tol_xyz[:, axis] for axis, pos in _walls(storage)])
    best = np.argmin(dist, axis=1)
    return np.where(dist[np.arange(len(best)), best] <= 1.0, best, -1)


def wall_contacts(cloud: Cloud, structure: np.ndarray, storage: Storage, err: SensorErrorModel,
                  cell_m: float, n_sigma: float | None = None, floor_by_plane: bool = False) -> WallContacts:
    """The wall contacts of a cloud (module docstring). structure: `pointcloud.structure_mask` of the cloud
    (True for wall and roof points); the cloud's points are in sample order with their times and sweep
    directions. No times or sweep directions: no contacts (the beams' order is unknown). cell_m: the grid
    the contacts will be used on; a contact the two beams locate more coarsely than the sensor's own error
    and than MAX_SLOPE times a cell (sparse beams: the lowest wall hit metres above the other beam's line)
    is not made. floor_by_plane: the floor test below by the floor's own tolerance (a noise correction)."""
    empty = WallContacts(np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int64))
    n = len(cloud.range_m)
    if n < 3 or cloud.t_s is None or cloud.sweep_dir is None:
        return empty
    p, d, r = cloud.points_w, cloud.dirs_w, np.asarray(cloud.range_m, dtype=float)
    t, sweep = np.asarray(cloud.t_s, dtype=float), np.asarray(cloud.sweep_dir)
    structure = np.asarray(structure, dtype=bool)
    k = structure_n_sigma(n) if n_sigma is None else n_sigma
    tol = plane_tolerances_m(cloud, err, k)  # (N, 3): each point's tolerance along the walls' and floor's normals
    wall = wall_index(p, tol, storage)
    on_wall = structure & (wall >= 0) & (p[:, 2] > 0.0) & (p[:, 2] < storage.height_m)
    dt = np.diff(t)
    step = float(np.median(dt[dt > 0])) if (dt > 0).any() else 0.0
    # adjacent[i]: samples i and i + 1 are neighbours in one sweep
    adjacent = (dt > 0) & (dt <= MAX_GAP_SAMPLES * step) & (sweep[1:] == sweep[:-1])
    ground = ~structure
    pairs = []
    for sign in (1, -1):  # the material after the wall hit (sign 1) or before it (sign -1) in time
        w = np.arange(n)
        m, m2 = w + sign, w + 2 * sign
        ok = (m2 >= 0) & (m2 < n)
        w, m, m2 = w[ok], m[ok], m2[ok]
        link = adjacent[np.minimum(w, m)] & adjacent[np.minimum(m, m2)]
        keep = on_wall[w] & ground[m] & ground[m2] & link  # material seen by two beams in a row
        pairs.append((w[keep], m[keep], np.full(int(keep.sum()), sign)))
    w, m, sign = (np.concatenate([a[i] for a in pairs]) for i in range(3))
    if not len(w):
        return empty
    axis = np.array([a for a, _ in _walls(storage)])[wall[w]]
    pos = np.array([c for _, c in _walls(storage)])[wall[w]]
    rows = np.arange(len(w))
    origin = p[m] - d[m] * r[m, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (pos - origin[rows, axis]) / d[m][rows, axis]  # along beam m to the wall plane
    reach = np.isfinite(s) & (s > r[m])  # the wall lies beyond the material hit
    z_cross = origin[:, 2] + s * d[m, 2]  # where beam m would have met the wall
    along = 1 - axis  # the wall's along-coordinate is the other horizontal axis
    along_w = p[w][rows, along]
    along_m = origin[rows, along] + s * d[m][rows, along]
    below = reach & (z_cross < p[w, 2])
    w_est = _first_on_plane(p, d, r, err, w, sign, wall, on_wall, adjacent, axis, pos)
    sig_w = vertical_sigma_m(err.range_sigma(r[w]), err.resolution_m, err.position_sigma_m, err.angle_sigma_rad,
                             r[w], d[w])
    sig_m = vertical_sigma_m(err.range_sigma(r[m]), err.resolution_m, err.position_sigma_m, err.angle_sigma_rad,
                             np.where(reach, s, r[m]), d[m])
    # The lowest "wall" hit may be material within its wall tolerance of the wall (the mask cannot tell them
    # apart): the material at the wall is then up to MAX_SLOPE times that tolerance higher.
    slack = MAX_SLOPE * tol[w][rows, axis]
    high = np.clip(np.maximum(p[w, 2], p[w_est, 2]) + k * sig_w + slack, 0.0, storage.height_m)
    low = np.minimum(np.clip(z_cross - k * sig_m, 0.0, None), high)
    # The beam short of the wall hit the floor: by default when that hit lies within k sig_m of it. sig_m is the
    # error of the beam carried on to the wall, which under a pointing error at range is metres and takes material
    # metres up for the floor (docs/design-notes.md, "Four biases of the noisy surface"); floor_by_plane (one of
    # the noise corrections, not yet the default) judges the hit by the floor's own tolerance instead, the one the
    # structure mask places the floor by.
    floor_tol = tol[m, 2] if floor_by_plane else k * sig_m
    floor = np.abs(p[m, 2]) <= floor_tol
    estimate = np.where(floor, 0.0, p[w_est, 2])
    # Material leaning on the wall rises (or is level) towards it, so its last hit short of the wall is no
    # higher than the wall seen above it. A last hit above that (a pile's crest metres from the wall, the
    # wall seen low behind it: the ground falls away unseen) marks no contact.
    last = np.where(w_est == w, m, w_est + sign)  # the material's last hit before the wall
    sig_last = vertical_sigma_m(err.range_sigma(r[last]), err.resolution_m, err.position_sigma_m,
                                err.angle_sigma_rad, r[last], d[last])
    leaning = p[last, 2] <= p[w_est, 2] + k * (sig_last + sig_w)
    as_measured = p[last, 2] <= p[w_est, 2]
    # The two beams locate the contact to their spacing at the wall; where that is coarser than both the
    # noise's own width and what a cell can hold, the lowest wall hit is only an upper bound (a 1-in-20
    # sample log of pile 1 put 1-4 m of material at walls where the truth is 0.05 m).
    resolved = p[w_est, 2] - np.maximum(z_cross, 0.0) <= np.maximum(k * (sig_w + sig_m) + slack, MAX_SLOPE * cell_m)
    a = 0.5 * (along_w + along_m)
    xy = np.where((axis == 0)[:, None], np.column_stack([pos, a]), np.column_stack([a, pos]))
    keep = below & leaning & resolved
    return WallContacts(xy[keep], np.clip(estimate[keep], low[keep], high[keep]), low[keep], high[keep],
                        wall[w][keep].astype(np.int64), as_measured[keep])


def _first_on_plane(p: np.ndarray, d: np.ndarray, r: np.ndarray, err: SensorErrorModel, w: np.ndarray,
                    sign: np.ndarray, wall: np.ndarray, on_wall: np.ndarray, adjacent: np.ndarray,
                    axis: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """Per contact, the first hit up its sweep from the lowest wall hit w (away from the material, which
    lies at w + sign) that lies on the wall plane within WALL_LIKE_SIGMAS of its own error along the
    normal; the last hit of the wall run when none does within MAX_WALK."""
    n = len(r)
    rows = np.arange(len(w))
    q = w.copy()
    active = np.ones(len(w), dtype=bool)
    for _ in range(MAX_WALK):
        dn = np.abs(d[q][rows, axis])
        sigma = np.sqrt((err.range_sigma(r[q]) * dn) ** 2 + (r[q] * err.angle_sigma_rad) ** 2 * (1.0 - dn**2)
                        + err.position_sigma_m**2 + err.resolution_m**2 / 12.0)
        inside = np.abs(p[q][rows, axis] - pos)
        active &= inside > WALL_LIKE_SIGMAS * sigma  # q still looks like material close to the wall
        nxt = q - sign
        ok = (nxt >= 0) & (nxt < n)
        nxt = np.clip(nxt, 0, n - 1)
        link = adjacent[np.clip(np.minimum(q, nxt), 0, n - 2)] & ok
        active &= link & on_wall[nxt] & (wall[nxt] == wall[w])
        if not active.any():
            break
        q = np.where(active, nxt, q)
    return q


def contact_heights_m(contacts: WallContacts, x_edges: np.ndarray, y_edges: np.ndarray) -> np.ndarray:
    """Per grid cell (edges x_edges, y_edges), the mean estimate of the wall contacts in it; NaN elsewhere."""
    nx, ny = len(x_edges) - 1, len(y_edges) - 1
    total, count = np.zeros((nx, ny)), np.zeros((nx, ny))
    if len(contacts):
        ix = np.clip(np.searchsorted(x_edges, contacts.xy_m[:, 0], side="right") - 1, 0, nx - 1)
        iy = np.clip(np.searchsorted(y_edges, contacts.xy_m[:, 1], side="right") - 1, 0, ny - 1)
        np.add.at(total, (ix, iy), contacts.height_m)
        np.add.at(count, (ix, iy), 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / count, np.nan)


def contact_ceiling_m(contacts: WallContacts, x_edges: np.ndarray, y_edges: np.ndarray) -> np.ndarray:
    """Per grid cell holding contacts, an upper bound on the ground at its centre: the lowest contact top
    (`high_m`) raised by MAX_SLOPE times the distance from the contact to the centre (the ground may rise
    that steeply inwards); NaN where no contact bounds the cell. For the interval's unseen term."""
    nx, ny = len(x_edges) - 1, len(y_edges) - 1
    out = np.full(nx * ny, np.inf)
    if len(contacts):
        ix = np.clip(np.searchsorted(x_edges, contacts.xy_m[:, 0], side="right") - 1, 0, nx - 1)
        iy = np.clip(np.searchsorted(y_edges, contacts.xy_m[:, 1], side="right") - 1, 0, ny - 1)
        cx, cy = 0.5 * (x_edges[ix] + x_edges[ix + 1]), 0.5 * (y_edges[iy] + y_edges[iy + 1])
        top = contacts.high_m + MAX_SLOPE * np.hypot(contacts.xy_m[:, 0] - cx, contacts.xy_m[:, 1] - cy)
        np.minimum.at(out, ix * ny + iy, top)
    return np.where(np.isfinite(out), out, np.nan).reshape(nx, ny)


def pin_contacts(heights: np.ndarray, contacts: WallContacts, x_edges: np.ndarray, y_edges: np.ndarray) -> np.ndarray:
    """The height grid with each unseen (non-finite) cell that holds wall contacts set to their mean estimate:
    known ground for the fill to carry the surface to. Seen cells are unchanged (the fit there stands)."""
    h = np.array(heights, dtype=float)
    wall = contact_heights_m(contacts, x_edges, y_edges)
    pin = ~np.isfinite(h) & np.isfinite(wall)
    h[pin] = wall[pin]
    return h


def contact_fill(heights: np.ndarray, contacts: WallContacts, x_edges: np.ndarray, y_edges: np.ndarray,
                 ceiling_m: np.ndarray | None = None, extension: Extension = Extension.BIHARMONIC) -> np.ndarray:
    """The unseen cells filled by the extension (`ground.unseen.bounded_fill`) from the seen cells and the
    wall contacts pinned in their cells (`pin_contacts`), held between the floor and ceiling_m."""
    return bounded_fill(pin_contacts(heights, contacts, x_edges, y_edges), ceiling_m, extension)



def contact_nodes(contacts: WallContacts) -> tuple[np.ndarray, np.ndarray]:
    """The contacts as surface nodes: (n, 3) points at the walls' feet at their estimated heights, and each
    one's 1-sigma height error (its interval's width as a uniform spread, for a fit that weights its points)."""
    points = np.column_stack([contacts.xy_m, contacts.height_m])
    sigma = np.maximum((contacts.high_m - contacts.low_m) / np.sqrt(12.0), 1e-3)
    return points, sigma
