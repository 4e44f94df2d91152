import numpy as np
import pytest
import trimesh


def frustum_mesh(base_r: float, top_r: float, height: float, centre_xy, segments: int = 512) -> trimesh.Trimesh:
    """Closed truncated cone standing on z = 0 (the issue's test pile)."""
    a = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    cx, cy = centre_xy
    bottom = np.column_stack([cx + base_r * np.cos(a), cy + base_r * np.sin(a), np.zeros(segments)])
    top = np.column_stack([cx + top_r * np.cos(a), cy + top_r * np.sin(a), np.full(segments, height)])
    verts = np.vstack([bottom, top, [[cx, cy, 0.0], [cx, cy, height]]])
    i = np.arange(segments)
    j = (i + 1) % segments
    side = np.vstack([np.column_stack([i, j, segments + j]), np.column_stack([i, segments + j, segments + i])])
    cb, ct = 2 * segments, 2 * segments + 1
    caps = np.vstack([np.column_stack([np.full(segments, cb), j, i]),
                      np.column_stack([np.full(segments, ct), segments + i, segments + j])])
    mesh = trimesh.Trimesh(verts, np.vstack([side, caps]), process=True)
    trimesh.repair.fix_normals(mesh)
    return mesh


def polygonal_frustum_volume(base_r, top_r, height, segments):
    """Exact volume of the tessellated frustum (regular polygon cross-sections)."""
    k = segments / 2 * np.sin(2 * np.pi / segments)
    return k * height / 3 * (base_r**2 + base_r * top_r + top_r**2)


@pytest.fixture
def cone_stl(tmp_path):
    path = tmp_path / "cone.stl"
    frustum_mesh(12.0, 2.0, 6.0, (30.0, 20.0)).export(path)
    return path
