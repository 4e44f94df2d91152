"""The surface as a closed triangle mesh (binary PLY, float64 vertices, colours by height), read by
CloudCompare, MeshLab, Blender, trimesh.

Each cell the report defines a height for becomes a fan of four triangles: one vertex at the cell's centre at
the cell's own height (the fitted surface there), one at each corner at the mean of the defined cells
sharing that corner. The solid is closed: vertical walls down to z = 0 along the edges of the defined region
and a floor at z = 0 under it, so it is watertight (every edge in two faces, consistent winding) and its
volume is meaningful. Where two defined cells touch only at a corner, the second gets its own copy of that
corner (same place and height), so no edge is shared by four faces.

Its volume is the report's grid volume exactly, by construction, not to a tolerance of the method: a fan
cell's volume is area x (centre/3 + 2/3 x mean of its corners), and summed over the cells each corner gives
back its mean to the cells that made it, so the corners add up to the cells' heights and the total is
area x sum of heights, eq. (7). What is left is floating-point rounding: VOLUME_RTOL. The vertices are
written as doubles (PLY's ``property double``), which trimesh, CloudCompare, MeshLab and Blender read, so the
file keeps that exactness; trimesh's own PLY writer would round them to float32, whose rounding of the fan's
apex moves the volume by an amount that depends on the slopes. A surface below the floor (noise under
z = 0) counts negative in both, as in the report; such a solid folds through its own floor there and is
watertight but not a valid volume to a strict mesh checker.

Coordinates are the storage frame W, metres (mesh tools have no CRS; docs/exports.md gives the site's
placement). PLY rather than STL (float32, no colours) or OBJ (text, three times larger).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from firmware_py.core.cli import UserError
from ground.exports.formats import ExportFormat, need
from ground.surface import Grid

VOLUME_RTOL = 1e-9
"""The solid's volume is the grid volume to this relative tolerance (double rounding over ~1e5 cells, ~1e-12;
the tests hold it)."""


MESH_BYTES_PER_CELL = 700
"""Peak memory of `write_mesh` per grid cell, measured with tracemalloc: 640 B at 240,000 cells (a 60 x 40 m
floor in 0.1 m cells); the file is ~160 B a cell."""


def check_mesh_memory(n_cells: int, max_bytes: int) -> None:
    """Refuse (one line) a mesh export whose construction would need more than max_bytes (the report's
    --max-grid-memory-mb), before the survey is computed."""
    need_b = n_cells * MESH_BYTES_PER_CELL
    if need_b > max_bytes:
        raise UserError(f"--export mesh of {n_cells:,} cells would need about {need_b / 2**20:,.0f} MiB, more than "
                        f"the {max_bytes / 2**20:,.0f} MiB allowed: use a larger --cell (or raise "
                        "--max-grid-memory-mb)")


def surface_solid(heights: np.ndarray, grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3), faces (F, 3)) of the closed solid under the defined cells (module docstring);
    both empty when no cell is defined. Outward normals (counter-clockwise seen from outside)."""
    h = np.asarray(heights, dtype=float)
    nx, ny = grid.shape
    if h.shape != (nx, ny):
        raise ValueError(f"heights shape {h.shape} differs from the grid's {grid.shape}")
    defined = np.isfinite(h)
    if not defined.any():
        return np.empty((0, 3)), np.empty((0, 3), dtype=np.int64)
    xe, ye = grid.x_edges, grid.y_edges
    # Corner heights: the mean of the defined cells around each corner (NaN where none is).
    hz = np.where(defined, h, 0.0)
    pad_h = np.pad(hz, 1)
    pad_n = np.pad(defined.astype(float), 1)
    total = pad_h[:-1, :-1] + pad_h[1:, :-1] + pad_h[:-1, 1:] + pad_h[1:, 1:]
    count = pad_n[:-1, :-1] + pad_n[1:, :-1] + pad_n[:-1, 1:] + pad_n[1:, 1:]
    with np.errstate(invalid="ignore", divide="ignore"):
        corner_z = total / count  # (nx + 1, ny + 1)
    cx, cy = np.meshgrid(xe, ye, indexing="ij")
    n_corners = (nx + 1) * (ny + 1)
    # A corner two cells touch only diagonally would carry four wall faces on its vertical edge (not a
    # manifold): the second cell gets its own copy of that corner, same place, same height.
    padded = np.pad(defined, 1)
    sw, se, nw, ne = padded[:-1, :-1], padded[1:, :-1], padded[:-1, 1:], padded[1:, 1:]
    pinch_a, pinch_b = sw & ne & ~se & ~nw, se & nw & ~sw & ~ne  # (nx + 1, ny + 1)
    pinch = (pinch_a | pinch_b).ravel()
    copy_of = np.full(n_corners, -1, dtype=np.int64)
    copy_of[pinch] = n_corners + np.arange(int(pinch.sum()))
    top = np.column_stack([cx.ravel(), cy.ravel(), np.nan_to_num(corner_z).ravel()])
    top = np.vstack([top, top[pinch]])
    floor = np.column_stack([top[:, :2], np.zeros(len(top))])
    ii, jj = np.nonzero(defined)
    centres = np.column_stack([0.5 * (xe[ii] + xe[ii + 1]), 0.5 * (ye[jj] + ye[jj + 1]), h[ii, jj]])

    def corner(i: np.ndarray, j: np.ndarray, copy: np.ndarray | None = None) -> np.ndarray:
        k = i * (ny + 1) + j
        return k if copy is None else np.where(copy[i, j], copy_of[k], k)

    # the cell north-east of an a-pinch and north-west of a b-pinch takes the copy
    c00, c10 = corner(ii, jj, pinch_a), corner(ii + 1, jj, pinch_b)
    c11, c01 = corner(ii + 1, jj + 1), corner(ii, jj + 1)
    f = len(top)  # floor vertex = top corner vertex + f
    m = 2 * f + np.arange(len(ii))
    faces = [np.column_stack(t) for t in (
        (m, c00, c10), (m, c10, c11), (m, c11, c01), (m, c01, c00),  # top fan, counter-clockwise from above
        (c00 + f, c11 + f, c10 + f), (c00 + f, c01 + f, c11 + f))]  # floor, clockwise from above
    # Walls: each cell edge (a -> b, counter-clockwise around the cell) whose other side is undefined.
    for (a, b), (di, dj) in (((c00, c10), (0, -1)), ((c10, c11), (1, 0)), ((c11, c01), (0, 1)),
                             ((c01, c00), (-1, 0))):
        edge = ~padded[ii + 1 + di, jj + 1 + dj]
        a, b = a[edge], b[edge]
        faces += [np.column_stack((a + f, b + f, b)), np.column_stack((a + f, b, a))]
    vertices = np.vstack([top, floor, centres])
    faces = np.vstack(faces).astype(np.int32)  # < 2^31 vertices: Grid caps the cells at MAX_CELLS
    used = np.zeros(len(vertices), dtype=bool)
    used[faces.ravel()] = True
    remap = np.cumsum(used, dtype=np.int32) - 1
    return vertices[used], remap[faces]


def write_mesh(heights: np.ndarray, grid: Grid, out: Path) -> Path:
    """Write the closed surface solid (module docstring) as binary little-endian PLY to out. With no defined
    cell there is no solid: ValueError (the report refuses such a survey before exports)."""
    need("matplotlib", ExportFormat.MESH)  # the colours
    from ground.render import height_colors

    vertices, faces = surface_solid(heights, grid)
    if len(faces) == 0:
        raise ValueError("no cell has a surface height: no mesh")
    vrec = np.empty(len(vertices), dtype=[("xyz", "<f8", (3,)), ("rgba", "u1", (4,))])
    vrec["xyz"] = vertices
    vrec["rgba"] = height_colors(vertices[:, 2])
    frec = np.empty(len(faces), dtype=[("n", "u1"), ("idx", "<i4", (3,))])
    frec["n"] = 3
    frec["idx"] = faces
    head = "\n".join([
        "ply", "format binary_little_endian 1.0",
        "comment pilescan surface solid, storage frame W, metres (x length, y width, z up from the floor)",
        f"element vertex {len(vrec)}", "property double x", "property double y", "property double z",
        "property uchar red", "property uchar green", "property uchar blue", "property uchar alpha",
        f"element face {len(frec)}", "property list uchar int vertex_indices", "end_header", ""])
    out.parent.mkdir(parents=True, exist_ok=True)
    with open(out, "wb") as fh:
        fh.write(head.encode("ascii"))
        fh.write(vrec.tobytes())
        fh.write(frec.tobytes())
    return out
