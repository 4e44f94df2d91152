"""Named, parametrised procedural stockpiles beyond the paper's generator, each with its exact volume.

Why: the paper's random pile (sitl.world.stockpile.generate) is one kind of surface; a calibrated
uncertainty needs piles the ground station finds hard: leaning on walls and in corners, low and
wide, steep and tall, several separate heaps, vertical faces, an undercut body and an empty floor.

Every shape is a `Stockpile` whose truth is computed from the very mesh the ray tracer sees
(`volume_under_mesh`: exact for an upward height field and for a closed body). Where a closed
formula exists it is returned too (`Shape.analytic_volume_m3`), so tests can check the meshes.

Most shapes are a "mesa" height field: z = clip(h - tan(alpha) d, 0, h), d the top-view distance
to a core rectangle (a point gives a cone, a segment a ridge with conical ends, a rectangle a
flat-topped pile). A core on a wall (x = 0 or y = 0) makes the pile lean on that wall; the part
beyond the wall does not exist. Its volume, for free slopes that stay inside the building:
V = a b h + sum(free side lengths) r h / 2 + (free corners) pi r^2 h / 12, with r = h / tan(alpha)
(a corner is free when both its sides are).

Every shape stays inside the building with its top at or below `max_top_m` (the caller derives it
from the flight altitude less a clearance); `make_shape` checks both.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
import trimesh

from firmware_py.core.storage import Storage
from sitl.world.stockpile import PileSpec, Stockpile, generate, heightfield_mesh, volume_under_mesh

MESH_RESOLUTION_M = 0.25
"""Vertex spacing of the height fields: the paper piles' (stockpile.PileSpec), 3 cells per 0.75 m survey cell."""
WALL_MARGIN_M = 0.5
"""The least floor left between a free-standing pile's foot and a wall (a loader's path)."""
SPHERE_SUBDIVISIONS = 4
"""Icosphere subdivisions: 5,120 faces, its volume within 0.3 % of 4/3 pi r^3."""


class Family(StrEnum):
    """Kinds of pile (each a function of the building, the highest top allowed and a seed)."""

    CONE = "cone"
    RIDGE = "ridge"
    CORNER = "corner"
    WALL = "wall"
    BAY = "bay"
    FLAT = "flat"
    STEEP = "steep"
    SEPARATE = "separate"
    IRREGULAR = "irregular"
    BOX = "box"
    SPHERE = "sphere"
    EMPTY = "empty"


@dataclass(frozen=True)
class Shape:
    """A generated pile: the mesh and its volume, with how it was made."""

    family: Family
    seed: int
    pile: Stockpile
    params: dict = field(default_factory=dict)
    analytic_volume_m3: float | None = None  # None: no closed formula (the paper's generator)
    height_field: bool = True  # False: a closed body a single height per cell cannot hold exactly

    @property
    def volume_m3(self) -> float:
        return self.pile.volume_m3

    @property
    def name(self) -> str:
        return f"{self.family.value}-{self.seed}"


# ----- the mesa primitive ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Mesa:
    """z = clip(h - tan(alpha) d, 0, h), d the top-view distance to the core [x0, x1] x [y0, y1]."""

    x0: float
    x1: float
    y0: float
    y1: float
    height_m: float
    repose_deg: float

    def __post_init__(self) -> None:
        if not (self.x0 <= self.x1 and self.y0 <= self.y1 and self.height_m > 0 and 0 < self.repose_deg < 90):
            raise ValueError(f"bad mesa {self}")

    @property
    def run_m(self) -> float:
        """Horizontal extent of a slope: r = h / tan(alpha)."""
        return self.height_m / math.tan(math.radians(self.repose_deg))

    def heights(self, px: np.ndarray, py: np.ndarray) -> np.ndarray:
        dx = np.maximum(np.maximum(self.x0 - px, px - self.x1), 0.0)
        dy = np.maximum(np.maximum(self.y0 - py, py - self.y1), 0.0)
        return np.clip(self.height_m - math.tan(math.radians(self.repose_deg)) * np.hypot(dx, dy), 0.0,
                       self.height_m)

    def footprint(self) -> tuple[float, float, float, float]:
        r = self.run_m
        return self.x0 - r, self.x1 + r, self.y0 - r, self.y1 + r

    def volume_m3(self, storage: Storage) -> float:
        """Exact volume inside the building (walls at x = 0, x = L, y = 0, y = W); ValueError when a free
        slope would cross a wall (the formula would not hold, and the pile would not be the one meant)."""
        lx, wy, h, r = storage.length_m, storage.width_m, self.height_m, self.run_m
        tol = 1e-9
        # sides: (on a wall?, length); a slope off a side not on a wall must stay inside
        on = {"x0": self.x0 <= tol, "x1": self.x1 >= lx - tol, "y0": self.y0 <= tol, "y1": self.y1 >= wy - tol}
        lo_x, hi_x, lo_y, hi_y = self.footprint()
        if (not on["x0"] and lo_x < -tol) or (not on["x1"] and hi_x > lx + tol) \
                or (not on["y0"] and lo_y < -tol) or (not on["y1"] and hi_y > wy + tol):
            raise ValueError(f"a free slope of {self} crosses a wall of the {storage} building")
        a, b = self.x1 - self.x0, self.y1 - self.y0
        sides = {"x0": b, "x1": b, "y0": a, "y1": a}
        v = a * b * h + sum(length for s, length in sides.items() if not on[s]) * r * h / 2
        corners = [("x0", "y0"), ("x1", "y0"), ("x1", "y1"), ("x0", "y1")]
        v += sum(not on[p] and not on[q] for p, q in corners) * math.pi * r * r * h / 12
        return v


def _grid(storage: Storage, resolution_m: float) -> tuple[np.ndarray, np.ndarray]:
    mx = max(2, math.ceil(storage.length_m / resolution_m) + 1)
    my = max(2, math.ceil(storage.width_m / resolution_m) + 1)
    return np.linspace(0.0, storage.length_m, mx), np.linspace(0.0, storage.width_m, my)


def _mesa_pile(storage: Storage, mesas: list[Mesa], source: str,
               resolution_m: float = MESH_RESOLUTION_M) -> tuple[Stockpile, float]:
    """Height field of the highest of the mesas (they must not overlap for the summed formula)."""
    xs, ys = _grid(storage, resolution_m)
    px, py = np.meshgrid(xs, ys, indexing="ij")
    z = np.zeros_like(px)
    for m in mesas:
        z = np.maximum(z, m.heights(px, py))
    mesh = heightfield_mesh(xs, ys, z)
    return Stockpile(mesh, volume_under_mesh(mesh), source), sum(m.volume_m3(storage) for m in mesas)


def _closed(mesh: trimesh.Trimesh, source: str) -> Stockpile:
    return Stockpile(mesh, volume_under_mesh(mesh), source)


# ----- the families -------------------------------------------------------------------------------------------


def _rng(family: Family, seed: int) -> np.random.Generator:
    return np.random.default_rng([list(Family).index(family), seed])


def _fit_height(storage: Storage, max_top_m: float, repose_deg: float, span_m: float, frac: float) -> float:
    """A pile height: frac of the highest allowed, lowered until a slope of run h / tan(alpha) fits span_m."""
    return min(frac * max_top_m, math.tan(math.radians(repose_deg)) * span_m)


def _centre(rng: np.random.Generator, storage: Storage, half_x: float, half_y: float) -> tuple[float, float]:
    """A centre whose footprint (half extents) keeps WALL_MARGIN_M from every wall."""
    lo_x, hi_x = half_x + WALL_MARGIN_M, storage.length_m - half_x - WALL_MARGIN_M
    lo_y, hi_y = half_y + WALL_MARGIN_M, storage.width_m - half_y - WALL_MARGIN_M
    return float(rng.uniform(lo_x, max(lo_x, hi_x))), float(rng.uniform(lo_y, max(lo_y, hi_y)))


def _free_span(storage: Storage) -> float:
    return min(storage.length_m, storage.width_m) / 2 - WALL_MARGIN_M


def cone(storage: Storage, max_top_m: float, seed: int) -> Shape:
    """A free-standing cone (angle of repose 30-37 deg)."""
    rng = _rng(Family.CONE, seed)
    alpha = float(rng.uniform(30.0, 37.0))
    h = _fit_height(storage, max_top_m, alpha, 0.8 * _free_span(storage), float(rng.uniform(0.6, 1.0)))
    r = h / math.tan(math.radians(alpha))
    cx, cy = _centre(rng, storage, r, r)
    m = Mesa(cx, cx, cy, cy, h, alpha)
    pile, v = _mesa_pile(storage, [m], f"cone(h={h:.2f} m, alpha={alpha:.1f} deg, at {cx:.1f},{cy:.1f})")
    return Shape(Family.CONE, seed, pile, {"height_m": h, "repose_deg": alpha}, v)


def ridge(storage: Storage, max_top_m: float, seed: int) -> Shape:
    """A free-standing ridge (windrow) with conical ends, along the building's length."""
    rng = _rng(Family.RIDGE, seed)
    alpha = float(rng.uniform(30.0, 37.0))
    h = _fit_height(storage, max_top_m, alpha, 0.8 * _free_span(storage), float(rng.uniform(0.5, 1.0)))
    r = h / math.tan(math.radians(alpha))
    length = float(rng.uniform(0.2, 0.9)) * max(0.0, storage.length_m - 2 * (r + WALL_MARGIN_M))
    cx, cy = _centre(rng, storage, length / 2 + r, r)
    m = Mesa(cx - length / 2, cx + length / 2, cy, cy, h, alpha)
    pile, v = _mesa_pile(storage, [m], f"ridge(h={h:.2f} m, length={length:.1f} m, alpha={alpha:.1f} deg)")
    return Shape(Family.RIDGE, seed, pile, {"height_m": h, "repose_deg": alpha, "length_m": length}, v)


def _mirror(storage: Storage, m: Mesa, flip_x: bool, flip_y: bool) -> Mesa:
    """The mesa reflected to another wall or corner (x -> L - x, y -> W - y)."""
    x0, x1 = (storage.length_m - m.x1, storage.length_m - m.x0) if flip_x else (m.x0, m.x1)
    y0, y1 = (storage.width_m - m.y1, storage.width_m - m.y0) if flip_y else (m.y0, m.y1)
    return Mesa(x0, x1, y0, y1, m.height_m, m.repose_deg)


def corner(storage: Storage, max_top_m: float, seed: int) -> Shape:
    """A pile in a building corner leaning on two walls: a quarter cone, or a quarter mesa whose flat top
    runs along both walls (the corner picked by the seed)."""
    rng = _rng(Family.CORNER, seed)
    alpha = float(rng.uniform(32.0, 38.0))
    span = 0.6 * min(storage.length_m, storage.width_m) - WALL_MARGIN_M
    h = _fit_height(storage, max_top_m, alpha, span, float(rng.uniform(0.6, 1.0)))
    r = h / math.tan(math.radians(alpha))
    a = float(rng.uniform(0.0, 1.0)) * max(0.0, span - r)  # flat top along the walls (0: a quarter cone)
    flip_x, flip_y = bool(rng.integers(2)), bool(rng.integers(2))
    m = _mirror(storage, Mesa(0.0, a, 0.0, a, h, alpha), flip_x, flip_y)
    pile, v = _mesa_pile(storage, [m], f"corner(h={h:.2f} m, top={a:.1f} m, alpha={alpha:.1f} deg)")
    return Shape(Family.CORNER, seed, pile, {"height_m": h, "repose_deg": alpha, "top_m": a,
                                             "corner": [int(flip_x), int(flip_y)]}, v)


def wall(storage: Storage, max_top_m: float, seed: int) -> Shape:
    """A half cone or a half windrow against one wall, its ends free (not in a corner)."""
    rng = _rng(Family.WALL, seed)
    alpha = float(rng.uniform(32.0, 38.0))
    along_x = bool(rng.integers(2))  # against a long wall (y = 0 or W) or an end wall (x = 0 or L)
    wall_len, depth = (storage.length_m, storage.width_m) if along_x else (storage.width_m, storage.length_m)
    h = _fit_height(storage, max_top_m, alpha, min(0.7 * depth, wall_len / 2) - WALL_MARGIN_M,
                    float(rng.uniform(0.6, 1.0)))
    r = h / math.tan(math.radians(alpha))
    length = float(rng.uniform(0.0, 0.8)) * max(0.0, wall_len - 2 * (r + WALL_MARGIN_M))
    c = float(rng.uniform(r + WALL_MARGIN_M + length / 2, wall_len - r - WALL_MARGIN_M - length / 2))
    flip = bool(rng.integers(2))
    base = Mesa(c - length / 2, c + length / 2, 0.0, 0.0, h, alpha) if along_x else \
        Mesa(0.0, 0.0, c - length / 2, c + length / 2, h, alpha)
    m = _mirror(storage, base, flip and not along_x, flip and along_x)
    pile, v = _mesa_pile(storage, [m], f"wall(h={h:.2f} m, length={length:.1f} m, alpha={alpha:.1f} deg)")
    return Shape(Family.WALL, seed, pile, {"height_m": h, "repose_deg": alpha, "length_m": length}, v)


def bay(storage: Storage, max_top_m: float, seed: int) -> Shape:
    """Material filling a bay against the back wall between two dividers: a closed prism, flat on top
    for a depth, then sloping to the floor at the angle of repose; its ends are vertical (where the
    dividers hold it; the dividers themselves are not simulated, so they add no volume), and the
    building's corners beside the bay are bare floor."""
    rng = _rng(Family.BAY, seed)
    alpha = float(rng.uniform(32.0, 38.0))
    along_x = storage.length_m >= storage.width_m  # the bays line the long wall
    wall_len, depth = (storage.length_m, storage.width_m) if along_x else (storage.width_m, storage.length_m)
    h = min(float(rng.uniform(0.6, 1.0)) * max_top_m, math.tan(math.radians(alpha)) * 0.5 * depth)
    r = h / math.tan(math.radians(alpha))
    top = float(rng.uniform(0.0, 1.0)) * max(0.0, 0.6 * depth - r)
    width = float(rng.uniform(0.25, 0.5)) * wall_len
    x0 = float(rng.uniform(0.1 * wall_len, 0.9 * wall_len - width))
    flip = bool(rng.integers(2))
    yz = [(0.0, 0.0), (0.0, h), (top, h), (top + r, 0.0)]
    if top == 0.0:
        yz = [(0.0, 0.0), (0.0, h), (r, 0.0)]
    pts = []
    for u in (x0, x0 + width):
        for y, z in yz:
            y_w = depth - y if flip else y
            pts.append((u, y_w, z) if along_x else (y_w, u, z))
    mesh = trimesh.convex.convex_hull(np.array(pts))
    area = h * top + h * r / 2
    pile = _closed(mesh, f"bay(h={h:.2f} m, width={width:.1f} m, top={top:.1f} m, alpha={alpha:.1f} deg)")
    return Shape(Family.BAY, seed, pile, {"height_m": h, "repose_deg": alpha, "width_m": width, "top_m": top},
                 area * width, height_field=True)


def flat(storage: Storage, max_top_m: float, seed: int) -> Shape:
    """A low, wide pile (0.5-1.5 m): a flat top over much of the floor, short slopes."""
    rng = _rng(Family.FLAT, seed)
    alpha = float(rng.uniform(25.0, 35.0))
    h = min(float(rng.uniform(0.5, 1.5)), max_top_m)
    r = h / math.tan(math.radians(alpha))
    a = float(rng.uniform(0.3, 0.8)) * (storage.length_m - 2 * (r + WALL_MARGIN_M))
    b = float(rng.uniform(0.3, 0.8)) * (storage.width_m - 2 * (r + WALL_MARGIN_M))
    cx, cy = _centre(rng, storage, a / 2 + r, b / 2 + r)
    m = Mesa(cx - a / 2, cx + a / 2, cy - b / 2, cy + b / 2, h, alpha)
    pile, v = _mesa_pile(storage, [m], f"flat(h={h:.2f} m, top {a:.1f} x {b:.1f} m, alpha={alpha:.1f} deg)")
    return Shape(Family.FLAT, seed, pile, {"height_m": h, "repose_deg": alpha, "top_m": [a, b]}, v)


def steep(storage: Storage, max_top_m: float, seed: int) -> Shape:
    """A tall cone or short ridge at the top of the angle of repose (38-40 deg), as high as allowed."""
    rng = _rng(Family.STEEP, seed)
    alpha = float(rng.uniform(38.0, 40.0))
    h = _fit_height(storage, max_top_m, alpha, 0.9 * _free_span(storage), float(rng.uniform(0.85, 1.0)))
    r = h / math.tan(math.radians(alpha))
    length = float(rng.uniform(0.0, 0.4)) * max(0.0, storage.length_m - 2 * (r + WALL_MARGIN_M))
    cx, cy = _centre(rng, storage, length / 2 + r, r)
    m = Mesa(cx - length / 2, cx + length / 2, cy, cy, h, alpha)
    pile, v = _mesa_pile(storage, [m], f"steep(h={h:.2f} m, length={length:.1f} m, alpha={alpha:.1f} deg)")
    return Shape(Family.STEEP, seed, pile, {"height_m": h, "repose_deg": alpha, "length_m": length}, v)


def separate(storage: Storage, max_top_m: float, seed: int) -> Shape:
    """2-4 cones with bare floor between them (footprints at least 1 m apart)."""
    rng = _rng(Family.SEPARATE, seed)
    n = int(rng.integers(2, 5))
    gap_m = 1.0
    mesas: list[Mesa] = []
    for _ in range(200):  # rejection sampling; the sizes shrink until n fit
        if len(mesas) == n:
            break
        alpha = float(rng.uniform(30.0, 37.0))
        span = 0.25 * min(storage.length_m, storage.width_m)
        h = _fit_height(storage, max_top_m, alpha, span, float(rng.uniform(0.3, 1.0)))
        r = h / math.tan(math.radians(alpha))
        cx, cy = _centre(rng, storage, r, r)
        if all(math.hypot(cx - m.x0, cy - m.y0) >= r + m.run_m + gap_m for m in mesas):
            mesas.append(Mesa(cx, cx, cy, cy, h, alpha))
    if len(mesas) < 2:
        raise ValueError(f"separate piles: could not place 2 cones in the {storage} building")
    pile, v = _mesa_pile(storage, mesas, f"separate({len(mesas)} cones, h "
                         + ", ".join(f"{m.height_m:.1f}" for m in mesas) + " m)")
    return Shape(Family.SEPARATE, seed, pile, {"n_piles": len(mesas), "heights_m": [m.height_m for m in mesas]}, v)


IRREGULAR_HEIGHT_RANGES_FRAC = ((0.15, 1.0), (0.1, 0.5), (0.4, 1.0), (0.0, 0.8))
"""Control-height ranges of the paper's generator as fractions of the top allowed (the paper: 1-7 m of ~9)."""


def irregular(storage: Storage, max_top_m: float, seed: int) -> Shape:
    """The paper's generator (Sec. 3.1) with this seed, a height range and wall policy from the seed;
    scaled down whole when the cubic overshoots the top allowed."""
    rng = _rng(Family.IRREGULAR, seed)
    lo, hi = IRREGULAR_HEIGHT_RANGES_FRAC[seed % len(IRREGULAR_HEIGHT_RANGES_FRAC)]
    zero_edges = bool(rng.integers(2))
    spacing = float(rng.choice([7.5, 10.0, 12.5]))
    spec = PileSpec(seed=1000 + seed, zero_edges=zero_edges, height_min_m=lo * max_top_m,
                    height_max_m=hi * max_top_m, control_spacing_m=spacing)
    pile = generate(spec, storage)
    mesh = pile.mesh
    top = float(mesh.vertices[:, 2].max())
    if top > max_top_m:
        mesh = mesh.copy()
        mesh.vertices[:, 2] *= max_top_m / top
    return Shape(Family.IRREGULAR, seed, Stockpile(mesh, volume_under_mesh(mesh), f"irregular({pile.source}, "
                 f"heights {spec.height_min_m:.1f}-{spec.height_max_m:.1f} m, spacing {spacing:g} m)"),
                 {"zero_edges": zero_edges, "height_range_m": [spec.height_min_m, spec.height_max_m],
                  "control_spacing_m": spacing})


def box(storage: Storage, max_top_m: float, seed: int) -> Shape:
    """A closed box with vertical faces (a stack of bales, a container) on the floor."""
    rng = _rng(Family.BOX, seed)
    h = float(rng.uniform(0.4, 1.0)) * max_top_m
    ex = float(rng.uniform(0.15, 0.5)) * storage.length_m
    ey = float(rng.uniform(0.15, 0.5)) * storage.width_m
    cx, cy = _centre(rng, storage, ex / 2, ey / 2)
    mesh = trimesh.creation.box(extents=(ex, ey, h),
                                transform=trimesh.transformations.translation_matrix((cx, cy, h / 2)))
    return Shape(Family.BOX, seed, _closed(mesh, f"box({ex:.1f} x {ey:.1f} x {h:.2f} m)"),
                 {"extents_m": [ex, ey, h]}, ex * ey * h)


def sphere(storage: Storage, max_top_m: float, seed: int) -> Shape:
    """A sphere resting on the floor (touching it at one point): undercut all round, so the surface seen
    from above stands over empty space. The ray tracer holds any closed triangle mesh."""
    rng = _rng(Family.SPHERE, seed)
    radius = min(float(rng.uniform(0.5, 1.0)) * max_top_m / 2, 0.4 * _free_span(storage))
    cx, cy = _centre(rng, storage, radius, radius)
    mesh = trimesh.creation.icosphere(subdivisions=SPHERE_SUBDIVISIONS, radius=radius)
    mesh.apply_translation((cx, cy, radius))
    return Shape(Family.SPHERE, seed, _closed(mesh, f"sphere(r={radius:.2f} m)"), {"radius_m": radius},
                 4.0 / 3.0 * math.pi * radius ** 3, height_field=False)


def empty(storage: Storage, max_top_m: float, seed: int) -> Shape:
    """No pile at all: a bare floor (true volume 0)."""
    return Shape(Family.EMPTY, seed, Stockpile(trimesh.Trimesh(), 0.0, "empty building"), {}, 0.0)


BUILDERS: dict[Family, Callable[[Storage, float, int], Shape]] = {
    Family.CONE: cone, Family.RIDGE: ridge, Family.CORNER: corner, Family.WALL: wall, Family.BAY: bay,
    Family.FLAT: flat, Family.STEEP: steep, Family.SEPARATE: separate, Family.IRREGULAR: irregular,
    Family.BOX: box, Family.SPHERE: sphere, Family.EMPTY: empty,
}


def make_shape(family: Family | str, storage: Storage, max_top_m: float, seed: int = 0) -> Shape:
    """The pile of this family and seed in this building, its top at most max_top_m; checked to lie
    inside the building, on the floor, and below max_top_m."""
    try:
        fam = Family(family)
    except ValueError:
        raise ValueError(f"unknown pile shape {family!r}; available: {', '.join(f.value for f in Family)}") from None
    if not (math.isfinite(max_top_m) and 0 < max_top_m < storage.height_m):
        raise ValueError(f"max pile top {max_top_m} m must be > 0 and below the {storage} building's roof")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed must be an integer >= 0, got {seed!r}")
    shape = BUILDERS[fam](storage, float(max_top_m), seed)
    problem = outside(shape.pile, storage, max_top_m)
    if problem:
        raise ValueError(f"{shape.name} in the {storage} building: {problem}")
    return shape


def outside(pile: Stockpile, storage: Storage, max_top_m: float, tol_m: float = 1e-6) -> str | None:
    """Why the pile does not fit (leaves the building, goes below the floor, above max_top_m), or None."""
    v = pile.mesh.vertices
    if len(v) == 0:
        return None
    lo, hi = v.min(axis=0), v.max(axis=0)
    if lo[0] < -tol_m or lo[1] < -tol_m or hi[0] > storage.length_m + tol_m or hi[1] > storage.width_m + tol_m:
        return f"spans x {lo[0]:.2f}..{hi[0]:.2f}, y {lo[1]:.2f}..{hi[1]:.2f} m, outside the floor"
    if lo[2] < -tol_m:
        return f"goes {-lo[2]:.2f} m below the floor"
    if hi[2] > max_top_m + tol_m:
        return f"its top {hi[2]:.2f} m is above the {max_top_m:.2f} m allowed"
    return None
