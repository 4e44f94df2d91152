"""The Delaunay triangulation the interpolating surface fits stand on, with its barycentric transforms computed in
one vectorised pass.

scipy computes each triangle's transform (the inverse of its edge matrix, what `find_simplex` and the
interpolators locate a point with) the first time it is asked, one LAPACK call per triangle: 0.05-0.1 s on the
report's ~37,000 triangles, 10 % of a report. In two dimensions the inverse is closed-form, so it is computed here
for all triangles at once (about 8 ms) and handed to the triangulation before anything asks for it. The same
degenerate triangles are marked (NaN) by the same test: scipy's, a 1-norm reciprocal condition number under
1000 eps. The values agree with scipy's to rounding (tests/ground/test_triangulation.py).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import Delaunay

RCOND_LIMIT = 1000.0 * np.finfo(float).eps
"""scipy's own limit (`scipy.spatial._qhull._get_barycentric_transforms`): below it a triangle's transform is NaN and
the point search steps around it."""


def barycentric_transforms(points: np.ndarray, simplices: np.ndarray) -> np.ndarray:
    """(n, 3, 2) for triangles simplices (n, 3) of points (m, 2): [T^-1; r] with T's columns the first two vertices
    less the last, r the last vertex (scipy's layout); NaN for a triangle whose T is singular to working precision."""
    p = np.asarray(points, dtype=float)
    s = np.asarray(simplices)
    r = p[s[:, 2]]
    a, c = p[s[:, 0], 0] - r[:, 0], p[s[:, 1], 0] - r[:, 0]  # T = [[a, c], [b, d]]
    b, d = p[s[:, 0], 1] - r[:, 1], p[s[:, 1], 1] - r[:, 1]
    det = a * d - b * c
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.stack([np.stack([d, -c], axis=-1), np.stack([-b, a], axis=-1)], axis=1) / det[:, None, None]
        norm = np.maximum(np.abs(a) + np.abs(b), np.abs(c) + np.abs(d))  # 1-norm: the largest column sum
        norm_inv = np.maximum(np.abs(d) + np.abs(b), np.abs(c) + np.abs(a)) / np.abs(det)
        singular = ~(1.0 / (norm * norm_inv) >= RCOND_LIMIT)  # NaN (0/0, inf/inf) counts as singular
    out = np.concatenate([inv, r[:, None, :]], axis=1)
    out[singular] = np.nan
    return out


def delaunay(xy: np.ndarray) -> Delaunay:
    """scipy's Delaunay triangulation of xy (n, 2), its transforms already in place (module docstring). Raises what
    scipy raises (QhullError, ValueError) for points that span no triangle."""
    tri = Delaunay(xy)
    if getattr(tri, "_transform", 0) is None and tri.points.shape[1] == 2:  # scipy's lazy slot, not yet filled;
        tri._transform = barycentric_transforms(tri.points, tri.simplices)  # another layout: scipy computes its own
    return tri
