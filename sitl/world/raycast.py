"""The simulated world: storage box (floor, walls, roof) plus a stockpile, ray traced with Embree.

Embree (through `embreex`) intersects in float32; over a building of tens of metres that is a few
micrometres, far below the LiDAR's 1 cm resolution (the tests check analytic hits to < 1 mm).
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np
from embreex import rtcore_scene as rtcs
from embreex.mesh_construction import TriangleMesh

from firmware_py.core.sensor import LIDARLITE_V3
from firmware_py.core.storage import Storage
from sitl.world.stockpile import Stockpile

"""Garmin LIDAR-Lite v3 range (Table 1)."""

GEOM_BUILDING, GEOM_PILE = 0, 1


def building_triangles(storage: Storage) -> np.ndarray:
    """The 12 triangles (12, 3, 3) of the inside of the box: floor, four walls, roof."""
    lx, wy, hz = storage.length_m, storage.width_m, storage.height_m
    c = np.array([[x, y, z] for z in (0.0, hz) for y in (0.0, wy) for x in (0.0, lx)])
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    tris = [(q[0], q[1], q[2]) for q in quads] + [(q[0], q[2], q[3]) for q in quads]
    return c[np.array(tris)]


@dataclass
class Hits:
    """Result of a batch of rays: range (NaN = no return), surface id and hit points in W."""

    range_m: np.ndarray
    geom_id: np.ndarray
    points_w: np.ndarray
    cos_incidence: np.ndarray | None = None  # |cos| of the angle between the beam and the surface normal


class World:
    """Storage + stockpile, queried with rays in the storage frame W."""

    def __init__(self, storage: Storage, pile: Stockpile | None = None,
                 max_range_m: float = LIDARLITE_V3.max_range_m) -> None:
        if not (np.isfinite(max_range_m) and max_range_m > 0):
            raise ValueError(f"max range must be > 0 m, got {max_range_m}")
        self.storage = storage
        self.pile = pile
        self.max_range_m = float(max_range_m)
        self._scene = rtcs.EmbreeScene()
        # Geometry ids follow insertion order: building first (GEOM_BUILDING), then the pile.
        TriangleMesh(self._scene, building_triangles(storage).astype(np.float32))
        self._pile_top_m = -math.inf
        if pile is not None and len(pile.mesh.faces):
            # by vertices and faces: embreex copies a flat triangle list element by element, three times as many
            # (the same triangles in the same order, so the same hits to the bit; docs/design-notes.md)
            TriangleMesh(self._scene, np.ascontiguousarray(pile.mesh.vertices, dtype=np.float32),
                         np.ascontiguousarray(pile.mesh.faces, dtype=np.int32))
            self._pile_top_m = float(pile.mesh.bounds[1, 2])
        self._one_d64 = np.empty(3)
        self._one_o32 = np.empty((1, 3), dtype=np.float32)
        self._one_d32 = np.empty((1, 3), dtype=np.float32)
        # The one-ray rows are shared: `serve` casts from two threads (the device bridge's LiDAR and the pose
        # drift's ray down), and a ray written by one between the other's write and its query returned the
        # wrong range (docs/design-notes.md, "A world shared by two threads").
        self._one_lock = threading.Lock()

    def buried(self, points_w: np.ndarray) -> np.ndarray:
        """Which points (N, 3) lie inside the stockpile: below its surface seen from the roof.

        A sensor there sees nothing (its window is in the material). It happens in the SITL, never
        in flight: the simulated vehicle stands on the floor, and a take-off spot the pile covers
        puts the LiDAR under the pile's surface, whose rays would otherwise reach the floor
        beneath it and give the ground station contradictory points.
        """
        p = np.asarray(points_w, dtype=float).reshape(-1, 3)
        out = np.zeros(len(p), dtype=bool)
        low = np.flatnonzero(p[:, 2] < self._pile_top_m)  # only these can be inside; in flight: none
        if len(low):
            top = np.column_stack([p[low, :2], np.full(len(low), self.storage.height_m - 1e-3)])
            res = self._scene.run(top.astype(np.float32), np.tile(np.float32([0.0, 0.0, -1.0]), (len(low), 1)),
                                  output=1)
            hit_z = top[:, 2] - res["tfar"].astype(np.float64)
            out[low] = (res["geomID"] == GEOM_PILE) & (res["primID"] >= 0) & (hit_z > p[low, 2])
        return out

    def cast(self, origins_w: np.ndarray, dirs_w: np.ndarray, max_range_m: float | None = None) -> Hits:
        """Cast rays (N, 3) from origins along unit directions; ranges beyond max are NaN."""
        o64 = np.asarray(origins_w, dtype=float).reshape(-1, 3)
        d64 = np.asarray(dirs_w, dtype=float).reshape(-1, 3)
        if o64.shape != d64.shape:
            raise ValueError(f"origins {o64.shape} and directions {d64.shape} differ")
        limit = self.max_range_m if max_range_m is None else float(max_range_m)
        if len(o64) == 0:
            return Hits(np.empty(0), np.empty(0, dtype=np.int32), np.empty((0, 3)))
        unit = d64 / np.linalg.norm(d64, axis=1)[:, None]
        res = self._scene.run(np.ascontiguousarray(o64, dtype=np.float32),
                              np.ascontiguousarray(unit, dtype=np.float32), output=1)
        r = res["tfar"].astype(np.float64)
        ok = (res["primID"] >= 0) & (r <= limit) & ~self.buried(o64)
        r = np.where(ok, r, np.nan)
        geom = np.where(ok, res["geomID"], -1).astype(np.int32)
        pts = o64 + unit * r[:, None]
        return Hits(r, geom, pts, _cos_incidence(res["Ng"], unit))

    def heights_below_m(self, xy_w: np.ndarray) -> np.ndarray:
        """The ground's height (the pile's, or the floor's 0) straight below each (x, y) of the storage frame, cast down
        from just under the roof: what a survey's heights are scored against."""
        xy = np.asarray(xy_w, dtype=float).reshape(-1, 2)
        top = self.storage.height_m - 1e-3
        origins = np.column_stack([xy, np.full(len(xy), top)])
        r = self.cast(origins, np.tile([0.0, 0.0, -1.0], (len(xy), 1)), max_range_m=self.storage.height_m).range_m
        return np.clip(top - np.nan_to_num(r, nan=top), 0.0, None)

    def cast_one_incidence(self, origin_w, dir_w) -> tuple[float, float]:
        """Range (NaN: no return) and |cos| of the incidence of one ray: the emulated LiDAR's path when a
        noise model needs the incidence (a full intersection query, unlike `cast_one`'s distance only)."""
        with self._one_lock:
            r = self._cast_one(origin_w, dir_w)
            if not math.isfinite(r):
                return r, 0.0
            res = self._scene.run(self._one_o32, self._one_d32, output=1)  # _cast_one left the ray in these rows
            return r, float(_cos_incidence(res["Ng"], self._one_d32.astype(np.float64))[0])

    def cast_one(self, origin_w, dir_w) -> float:
        """Range of one ray, m (NaN when there is no return within the max range).

        The emulated LiDAR's path, one ray per sample (its acquisition times and servo angle are only
        known as the payload runs): Embree's distance-only query on preallocated float32 rows, the
        direction normalised exactly as `cast` does (numpy's dot, whose rounding plain floats do not
        reproduce), so the float32 ray, and the range, are bit for bit those of `cast`. Thread-safe: the rows
        are written and queried under one lock.
        """
        with self._one_lock:
            return self._cast_one(origin_w, dir_w)

    def _cast_one(self, origin_w, dir_w) -> float:
        """`cast_one` with the lock held."""
        if origin_w[2] < self._pile_top_m and self.buried(origin_w)[0]:
            return math.nan
        d64, o32, d32 = self._one_d64, self._one_o32, self._one_d32
        d64[0], d64[1], d64[2] = dir_w
        norm = math.sqrt(float(d64 @ d64))
        row = o32[0]
        row[0], row[1], row[2] = origin_w
        row = d32[0]
        row[0], row[1], row[2] = d64[0] / norm, d64[1] / norm, d64[2] / norm
        r = float(self._scene.run(o32, d32, query="DISTANCE")[0])
        return r if r <= self.max_range_m else math.nan  # a miss reads Embree's initial tfar, 1e37


def _cos_incidence(ng: np.ndarray, unit_dirs: np.ndarray) -> np.ndarray:
    """|cos| of the angle between unit beam directions and (unnormalised) geometric normals; 0 where none."""
    ng = np.asarray(ng, dtype=np.float64).reshape(-1, 3)
    norm = np.linalg.norm(ng, axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        c = np.abs(np.einsum("ij,ij->i", ng, unit_dirs)) / norm
    return np.where(norm > 0, np.clip(c, 0.0, 1.0), 0.0)
