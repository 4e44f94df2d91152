"""Stockpiles: the paper's random generator (Sec. 3.1), mesh loading, exact true volume.

A stockpile is a triangle mesh in the storage frame W (metres, z up). Its true volume is computed
exactly from the mesh the ray tracer sees, so the "truth" and the "world" can never disagree.
"""

from __future__ import annotations

import io
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy.interpolate import RegularGridInterpolator

from firmware_py.core.safe_read import read_bounded
from firmware_py.core.storage import Storage

# Seeds for the paper's two piles in the default 60 x 40 m building, chosen once (tools/find_pile_seeds.py
# searches them) so the true volumes fall within 2 % of Table 1: 7193.5 and 8763.6 m^3.
PAPER_PILES = {
    "1": {"zero_edges": True, "seed": 10, "table1_volume_m3": 7193.5},
    "2": {"zero_edges": False, "seed": 20, "table1_volume_m3": 8763.6},
}


@dataclass(frozen=True)
class PileSpec:
    """Parameters of the paper's random pile generator.

    Attributes:
        seed: random seed of the control-point heights.
        zero_edges: heights on the walls forced to 0 (the paper's pile 1) or random (pile 2).
        height_min_m, height_max_m: range of the random control heights (paper: 1-7 m).
        control_spacing_m: target spacing of the regular grid of control points.
        mesh_resolution_m: vertex spacing of the triangulated surface.
    """

    seed: int = 0
    zero_edges: bool = True
    height_min_m: float = 1.0
    height_max_m: float = 7.0
    control_spacing_m: float = 10.0
    mesh_resolution_m: float = 0.25

    def __post_init__(self) -> None:
        if not (0 <= self.height_min_m <= self.height_max_m and math.isfinite(self.height_max_m)):
            raise ValueError(f"pile heights must satisfy 0 <= min <= max, got {self.height_min_m}, "
                             f"{self.height_max_m}")
        for name in ("control_spacing_m", "mesh_resolution_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be > 0, got {v}")


@dataclass(frozen=True)
class Stockpile:
    """A pile mesh with its exact volume and where it came from."""

    mesh: trimesh.Trimesh
    volume_m3: float
    source: str

    @property
    def max_height_m(self) -> float:
        return float(self.mesh.vertices[:, 2].max()) if len(self.mesh.vertices) else 0.0


def control_heights(spec: PileSpec, storage: Storage) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random heights on a regular grid of control points spread over the floor (paper Fig. 5a)."""
    # At least 4 points a side: a cubic needs them, and a small building still gets a pile.
    nx = max(4, round(storage.length_m / spec.control_spacing_m) + 1)
    ny = max(4, round(storage.width_m / spec.control_spacing_m) + 1)
    xs = np.linspace(0.0, storage.length_m, nx)
    ys = np.linspace(0.0, storage.width_m, ny)
    rng = np.random.default_rng(spec.seed)
    h = rng.uniform(spec.height_min_m, spec.height_max_m, size=(nx, ny))
    if spec.zero_edges:
        h[0, :] = h[-1, :] = h[:, 0] = h[:, -1] = 0.0
    return xs, ys, h


def heightfield_mesh(xs: np.ndarray, ys: np.ndarray, z: np.ndarray) -> trimesh.Trimesh:
    """Upward-facing triangulated surface through z[i, j] at (xs[i], ys[j])."""
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    vertices = np.column_stack([gx.ravel(), gy.ravel(), z.ravel()])
    idx = np.arange(gx.size).reshape(gx.shape)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    return trimesh.Trimesh(vertices=vertices, faces=faces, process=False)


def surface_height(spec: PileSpec, storage: Storage) -> Callable[[np.ndarray], np.ndarray]:
    """The paper's pile surface as a function of (n, 2) floor positions: the cubic through the control
    grid, clipped at the floor. `generate` triangulates it; an evaluation can ask it for exact heights."""
    xs, ys, h = control_heights(spec, storage)
    surface = RegularGridInterpolator((xs, ys), h, method="cubic")

    def height(xy: np.ndarray) -> np.ndarray:
        return np.clip(surface(np.asarray(xy, dtype=float).reshape(-1, 2)), 0.0, None)
    return height


def generate(spec: PileSpec, storage: Storage) -> Stockpile:
    """The paper's pile: random control heights, a cubic surface through them, triangulated.

    The cubic is the C2 tensor-product spline through the control grid; where it undershoots
    below the floor (next to zero-height walls) it is clipped to 0, as material cannot.
    """
    height = surface_height(spec, storage)
    mx = max(2, math.ceil(storage.length_m / spec.mesh_resolution_m) + 1)
    my = max(2, math.ceil(storage.width_m / spec.mesh_resolution_m) + 1)
    gx, gy = np.linspace(0.0, storage.length_m, mx), np.linspace(0.0, storage.width_m, my)
    px, py = np.meshgrid(gx, gy, indexing="ij")
    z = height(np.column_stack([px.ravel(), py.ravel()])).reshape(px.shape)
    mesh = heightfield_mesh(gx, gy, z)
    return Stockpile(mesh, volume_under_mesh(mesh), f"generated(seed={spec.seed}, "
                     f"zero_edges={spec.zero_edges})")


def paper_pile_spec(name: str) -> PileSpec:
    """The generator settings of stockpile "1" or "2" of the paper."""
    if name not in PAPER_PILES:
        raise ValueError(f"unknown stockpile {name!r}: use 1, 2 or a path to an STL/OBJ mesh")
    p = PAPER_PILES[name]
    return PileSpec(seed=p["seed"], zero_edges=p["zero_edges"])


def paper_pile(name: str, storage: Storage | None = None) -> Stockpile:
    """Stockpile "1" or "2" of the paper."""
    pile = generate(paper_pile_spec(name), storage or Storage())
    return Stockpile(pile.mesh, pile.volume_m3, f"paper pile {name} ({pile.source})")


def volume_under_mesh(mesh: trimesh.Trimesh) -> float:
    """Exact volume between the mesh and the floor z = 0.

    By the divergence theorem with F = (0, 0, z), sum over faces of (signed projected area x
    centroid height) is exact for a closed mesh (its enclosed volume) and for an open height field
    facing up (the volume under it). Faces on the floor contribute nothing either way.
    """
    tri = mesh.triangles
    if len(tri) == 0:
        return 0.0
    return float(np.sum(_projected_areas(tri) * tri[:, :, 2].mean(axis=1)))


def _projected_areas(tri: np.ndarray) -> np.ndarray:
    """Signed top-view areas of triangles (N, 3, 3): positive when the face looks up."""
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    return 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])


def _is_height_field(mesh: trimesh.Trimesh) -> bool:
    """True when no two faces overlap in top view (projected areas all of one sign, summing up)."""
    area_z = _projected_areas(mesh.triangles)
    return bool(np.all(area_z >= -1e-9 * max(1.0, np.abs(area_z).max())))


MAX_MESH_TRIANGLES = 2_000_000
"""Most triangles a stockpile mesh may have: 26 times the paper piles' 77k (0.25 m vertex spacing over
60 x 40 m), a 60 x 40 m pile at 5 cm spacing (1.9M), which is finer than the LiDAR's beam sees (8 mrad: a
4 cm spot at 5 m). trimesh needs ~200 bytes a triangle to load and process one, 0.4 GB here."""
BINARY_STL_HEAD_BYTES = 84
"""A binary STL: 80-byte header, uint32 triangle count, then 50 bytes per triangle."""
BINARY_STL_TRIANGLE_BYTES = 50
TEXT_MESH_BYTES_PER_TRIANGLE = 512
"""Upper bound of a text mesh's bytes per triangle (ASCII STL at full float precision is ~300; OBJ, PLY
and OFF share vertices and need less): bounds the file size before it is read."""
MAX_MESH_BODIES = 100
"""Most separate closed bodies a stockpile mesh may have: a building holds tens of piles at most, and every two
bodies are checked for shared material (100 bodies: 4,950 pairs; 2,000 took 42 s, 20,000 would take hours)."""
MIN_MESH_VOLUME_M3 = 1e-6
"""Least volume a stockpile mesh must hold: a cube of the LIDAR-Lite's 1 cm resolution. Less, its triangles are
flat or doubled (a triangle listed twice is "closed" with volume 0), yet the rays still hit them."""
FLOOR_TOLERANCE_M = 0.01
"""A closed body whose lowest point is higher than this above the floor floats: the LIDAR-Lite's range
resolution, so a gap a survey could never see is not a reason to refuse."""


def max_mesh_bytes(suffix: str, max_triangles: int) -> int:
    """The largest file of this type that can hold max_triangles (checked before it is read)."""
    if suffix == ".stl":
        return max(BINARY_STL_HEAD_BYTES + BINARY_STL_TRIANGLE_BYTES * max_triangles,
                   TEXT_MESH_BYTES_PER_TRIANGLE * max_triangles)
    return TEXT_MESH_BYTES_PER_TRIANGLE * max_triangles + 1024


def _checked_stl(data: bytes, path: Path) -> None:
    """A binary STL must be exactly as long as its triangle count says; anything else must be ASCII STL.

    trimesh guesses otherwise (and a failed guess ends in an import error of a text-encoding detector),
    and a file with trailing or missing bytes is damaged: its triangles cannot be vouched for.
    """
    if len(data) >= BINARY_STL_HEAD_BYTES:
        n = int.from_bytes(data[80:84], "little")
        want = BINARY_STL_HEAD_BYTES + BINARY_STL_TRIANGLE_BYTES * n
        if len(data) == want:
            return
    else:
        n, want = 0, 0
    if data[:5].lower() == b"solid":
        try:
            data.decode("ascii")
            return
        except UnicodeDecodeError as exc:
            raise ValueError(f"stockpile mesh {path} starts like an ASCII STL but has a non-ASCII byte at "
                             f"{exc.start}, and is not a binary STL either (it declares {n:,} triangles = "
                             f"{want:,} bytes, the file has {len(data):,})") from None
    if n and len(data) > want:
        raise ValueError(f"stockpile mesh {path} is a binary STL declaring {n:,} triangles ({want:,} bytes) "
                         f"followed by {len(data) - want:,} trailing bytes: damaged or two files in one; "
                         "cut it to its declared length if the triangles are complete")
    raise ValueError(f"stockpile mesh {path} is neither an ASCII STL nor a complete binary STL (it declares "
                     f"{n:,} triangles = {want:,} bytes, the file has {len(data):,})")


def _read_mesh(path: Path, max_triangles: int) -> trimesh.Trimesh:
    """The file's triangles, unprocessed: bounded read, format checked, no NaN merged away."""
    suffix = path.suffix.lower()
    data = read_bounded(path, max_mesh_bytes(suffix, max_triangles), "stockpile mesh")
    if suffix == ".stl":
        _checked_stl(data, path)
    elif suffix in {".obj", ".off"}:
        try:
            data.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise ValueError(f"stockpile mesh {path} is not UTF-8 text (byte {exc.start})") from None
    try:
        mesh = trimesh.load(io.BytesIO(data), file_type=suffix[1:], force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for bad files
        raise ValueError(f"cannot read stockpile mesh {path}: {type(exc).__name__}: {exc}") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"stockpile mesh {path} has no triangles")
    if len(mesh.faces) > max_triangles:
        raise ValueError(f"stockpile mesh {path} has {len(mesh.faces):,} triangles, more than the "
                         f"{max_triangles:,} allowed")
    faces = np.asarray(mesh.faces)
    if faces.min() < 0 or faces.max() >= len(mesh.vertices):  # a PLY's indices are not checked by the reader
        raise ValueError(f"stockpile mesh {path} has faces naming vertices it does not have (indices "
                         f"{int(faces.min())} to {int(faces.max())} of {len(mesh.vertices)} vertices)")
    used = mesh.vertices[np.unique(faces)]
    bad = ~np.isfinite(used)
    if bad.any():
        what = "NaN" if np.isnan(used).any() else "infinite"
        raise ValueError(f"stockpile mesh {path} has {int(bad.any(axis=1).sum())} vertices with {what} "
                         "coordinates")
    return trimesh.Trimesh(mesh.vertices, mesh.faces, process=True)


def _edges_cross(a: trimesh.Trimesh, b: trimesh.Trimesh) -> bool:
    """True when an edge of a passes through a face of b (strictly inside the edge)."""
    seg = a.vertices[a.edges_unique]
    d = seg[:, 1] - seg[:, 0]
    length = np.linalg.norm(d, axis=1)
    keep = length > 0
    if not keep.any():
        return False
    origins, dirs, length = seg[keep, 0], d[keep] / length[keep, None], length[keep]
    loc, ray, _ = b.ray.intersects_location(origins, dirs, multiple_hits=False)
    if len(ray) == 0:
        return False
    t = np.einsum("ij,ij->i", loc - origins[ray], dirs[ray])
    eps = 1e-6 * max(1.0, float(np.ptp(b.bounds)))
    return bool(np.any((t > eps) & (t < length[ray] - eps)))


def _overlap(a: trimesh.Trimesh, b: trimesh.Trimesh) -> bool:
    """Do two closed, outward-facing bodies share material: surfaces crossing, or one inside the other."""
    if np.any(a.bounds[1] <= b.bounds[0]) or np.any(b.bounds[1] <= a.bounds[0]):
        return False
    if _edges_cross(a, b) or _edges_cross(b, a):
        return True
    return bool(b.contains(a.vertices).all() or a.contains(b.vertices).all())


def _closed_volume(mesh: trimesh.Trimesh, path: Path, floor_tolerance_m: float) -> float:
    """Volume of a closed mesh whose bodies each rest on the floor and share no material.

    Summing overlapping shells would count their shared material twice, and a body floating above the
    floor is not material a survey could measure from above (the space below it would be seen as pile).
    """
    if mesh.volume < 0:  # inside out throughout
        mesh.invert()
    bodies = [m for m in mesh.split(only_watertight=False) if m.volume > 0]  # negative: a cavity's shell
    for i, body in enumerate(bodies, 1):
        lo = float(body.bounds[0, 2])
        if lo > floor_tolerance_m:
            raise ValueError(f"stockpile mesh {path}: closed body {i} of {len(bodies)} ({body.volume:.1f} m^3) "
                             f"floats {lo:.2f} m above the floor; a stockpile rests on the floor")
    for i, a in enumerate(bodies, 1):
        for j in range(i, len(bodies)):
            b = bodies[j]
            if _overlap(a, b):
                raise ValueError(
                    f"stockpile mesh {path}: closed bodies {i} ({a.volume:.1f} m^3) and {j + 1} ({b.volume:.1f} m^3) "
                    f"overlap, so their sum ({a.volume + b.volume:.1f} m^3) counts shared material twice; merge "
                    "them into one closed surface (a boolean union)")
    return float(mesh.volume)


def load_mesh(path: str | Path, storage: Storage, *, max_triangles: int = MAX_MESH_TRIANGLES,
              floor_tolerance_m: float = FLOOR_TOLERANCE_M) -> Stockpile:
    """Load an STL/OBJ/PLY pile (z up, metres, storage frame) and check it is what it claims.

    A closed mesh is taken as the material body: each of its bodies must rest on the floor and no two
    may overlap. An open mesh must be an upward height field (a surface over the floor), whose volume
    is the volume under it. Anything else is refused with a message, because its "volume under the
    surface" would be ambiguous. The file is read bounded (a size limit from max_triangles, before
    reading; only regular files), and NaN or infinite vertices are named.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"stockpile mesh not found: {path}" if not path.exists() else
                         f"stockpile mesh not found: {path} is not a regular file")
    with np.errstate(all="ignore"):  # a degenerate mesh's mass properties divide by its zero volume: refused below
        return _checked_pile(_read_mesh(path, max_triangles), path, storage, floor_tolerance_m)


def _m(v: float) -> str:
    """A coordinate for a message: centimetres, or three digits when it is far beyond any building."""
    return f"{v:.2f}" if abs(v) < 1e6 else f"{v:.3g}"


def _checked_pile(mesh: trimesh.Trimesh, path: Path, storage: Storage, floor_tolerance_m: float) -> Stockpile:
    v = mesh.vertices
    tol = 1e-6 * max(storage.length_m, storage.width_m)
    lo, hi = v.min(axis=0), v.max(axis=0)
    if (lo[0] < -tol or lo[1] < -tol or hi[0] > storage.length_m + tol or hi[1] > storage.width_m + tol
            or lo[2] < -tol or hi[2] >= storage.height_m):
        raise ValueError(
            f"stockpile mesh {path} spans x {_m(lo[0])}..{_m(hi[0])}, y {_m(lo[1])}..{_m(hi[1])}, "
            f"z {_m(lo[2])}..{_m(hi[2])} m: it must lie inside the {storage} building, on the floor "
            "(storage frame W: metres, z up)")
    if mesh.is_watertight:
        if mesh.body_count > MAX_MESH_BODIES:  # every pair is checked for overlap: the square of the count
            raise ValueError(f"stockpile mesh {path} is {mesh.body_count:,} separate closed bodies, more than the "
                             f"{MAX_MESH_BODIES} piles a building holds; merge them into fewer closed surfaces")
        volume = _closed_volume(mesh, path, floor_tolerance_m)
    else:
        if not _is_height_field(mesh):
            mesh.faces = mesh.faces[:, ::-1]
            if not _is_height_field(mesh):
                raise ValueError(f"stockpile mesh {path} is neither closed nor a height field over the "
                                 "floor; its volume would be ambiguous")
        volume = volume_under_mesh(mesh)
    if not volume > MIN_MESH_VOLUME_M3:  # the rays would still hit its triangles: a truth of 0 would be wrong
        raise ValueError(f"stockpile mesh {path} encloses no volume ({volume:.3g} m^3): its triangles are flat, "
                         "doubled or degenerate, not the surface of a pile")
    return Stockpile(mesh, volume, f"mesh {path.name}")


def resolve(name_or_path: str, storage: Storage) -> Stockpile:
    """'1' / '2' for the paper's piles, anything else a mesh path."""
    if name_or_path in PAPER_PILES:
        return paper_pile(name_or_path, storage)
    if Path(name_or_path).suffix.lower() in {".stl", ".obj", ".ply", ".off", ".glb"}:
        return load_mesh(name_or_path, storage)
    raise ValueError(f"unknown stockpile {name_or_path!r}: use 1, 2 or a path to an STL/OBJ mesh")
