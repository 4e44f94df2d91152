"""The storage building: a closed rectangular box in the storage frame W.

Part of the sample-log header contract, so it lives beside the log: the SITL builds the world
from it and the ground station removes walls and roof with it.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from firmware_py.core.numbers import is_finite_number

SURFACE_NAMES = ("the wall x = 0", "the wall x = L", "the wall y = 0", "the wall y = W", "the roof")
"""`Storage.nearest_surface`'s names, in its order."""


@dataclass(frozen=True)
class Storage:
    """Inside dimensions of the building, m: x in [0, length], y in [0, width], z in [0, height]."""

    length_m: float = 60.0
    width_m: float = 40.0
    height_m: float = 15.0

    def __post_init__(self) -> None:
        for name in ("length_m", "width_m", "height_m"):
            v = getattr(self, name)
            # bool is an int to Python, but a JSON `true` is not 1 m: refuse it by type
            if not (is_finite_number(v)
                    and 0.5 <= v <= 10_000):
                raise ValueError(f"storage {name.removesuffix('_m')} must be 0.5-10000 m, got {v}")

    @property
    def floor_area_m2(self) -> float:
        return self.length_m * self.width_m

    def nearest_surface(self, points_w_m) -> tuple[int, float, str] | None:
        """Of points in W ((N, 3), m), the one nearest a wall or the roof: (its index, its signed distance,
        negative outside, the surface's name); None when no point is finite. The floor is left out: a vehicle
        takes off from it and lands on it."""
        p = np.asarray(points_w_m, dtype=float).reshape(-1, 3)
        d = np.column_stack([p[:, 0], self.length_m - p[:, 0], p[:, 1], self.width_m - p[:, 1],
                             self.height_m - p[:, 2]])
        d[~np.isfinite(p).all(axis=1)] = np.inf
        if not np.isfinite(d).any():
            return None
        i, j = np.unravel_index(int(np.argmin(d)), d.shape)
        return int(i), float(d[i, j]), SURFACE_NAMES[j]

    def to_dict(self) -> dict:
        return {"length_m": self.length_m, "width_m": self.width_m, "height_m": self.height_m}

    @classmethod
    def from_dict(cls, d: dict) -> Storage:
        """From a header's ``storage`` object; KeyError for a missing key, ValueError naming a value that
        is not a number (no coercion: a JSON boolean or string is not a dimension)."""
        if not isinstance(d, dict):
            raise ValueError(f"storage must be a JSON object, got {type(d).__name__}")
        vals = []
        for name in ("length_m", "width_m", "height_m"):
            v = d[name]
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise ValueError(f"storage {name} must be a number, got {v!r}")
            vals.append(float(v))
        return cls(*vals)

    @classmethod
    def parse(cls, text: str) -> Storage:
        """Parse 'LxWxH' in metres, e.g. '60x40x15'."""
        m = re.fullmatch(r"\s*([0-9.eE+-]+)\s*[xX*]\s*([0-9.eE+-]+)\s*[xX*]\s*([0-9.eE+-]+)\s*", text)
        if not m:
            raise ValueError(f"storage must look like LxWxH in metres (e.g. 60x40x15), got {text!r}")
        try:
            vals = [float(g) for g in m.groups()]
        except ValueError:
            raise ValueError(f"storage must look like LxWxH in metres (e.g. 60x40x15), got {text!r}") \
                from None
        return cls(*vals)

    def __str__(self) -> str:
        return f"{self.length_m:g}x{self.width_m:g}x{self.height_m:g} m"
