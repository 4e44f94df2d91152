"""The surface file's contract (`surface.npz` in a report directory): its name, format, versions and bounds,
and the checked raw read every program shares.

The ground station writes it (`ground.surface_file`: a later survey's base, `compare`) and the coverage
planner reads it (`sitl.missions.surveyed_surface`, `sitl.missions.gaps`); neither imports the other, so what
they both must agree on lives here. The file holds a float64 `heights_m` grid and one JSON string `meta` (no
pickles); what each reader needs of `meta` it checks itself, each number by `meta_number` (one check and one
wording for both readers). Version 2 adds `fitted`, a bool grid of the cells whose height was fitted to the
survey's points (the rest were filled by the empty-cell policy: what the survey could not see, which a gap
re-flight must see); version 1 files are still read (`fitted` then unknown).
"""

from __future__ import annotations

import io
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from firmware_py.core.safe_read import InputError, read_bounded

SURFACE_FILE = "surface.npz"
FORMAT = "pilescan-surface"
FORMAT_VERSION = 2
"""Written by this version: heights, the fitted cells' mask and the metadata."""
READ_VERSIONS = (1, 2)
"""Version 1 (before the fitted mask) is still read."""
_ARRAYS = {1: {"heights_m", "meta"}, 2: {"heights_m", "fitted", "meta"}}
MIN_GRID_CELL_M = 0.01
"""Finest grid cell of a surface (a LIDAR-Lite's resolution): finer, a grid's cell count leaves the integers."""
MIN_BUILDING_M = 1e-3
"""Least length, width or height of a surface file's building (a millimetre: no building, but no zero to divide by)."""
SEEN_RADIUS_M = 1.0
"""A floor cell counts as seen when a point lies this near it: the coverage planner's test of a flight, the gap
re-flight's of a report, and the report's bridged area (cells inside R_a with no point this near). The paper's
baseline sweep (5 rad/s, 0.67 Hz, two fans a period) flown at 1 m/s puts fans 0.75 m apart, so its legs are seen
between fans; a flight fast enough to open gaps over twice this is not."""
MAX_GRID_CELLS = 25_000_000
"""The most cells a height grid may have (a header may claim a big building with fine cells: refuse, not
MemoryError); the ground's Grid enforces it too."""
MAX_SURFACE_BYTES = 17 * MAX_GRID_CELLS + 1_000_000
"""Largest surface file read: two float64 grids and a bool grid of the most cells a grid allows, plus the
metadata."""


@dataclass(frozen=True)
class RawSurface:
    """A surface file's arrays and metadata as read, before any reader's own field checks."""

    heights_m: np.ndarray = field(compare=False)
    meta: dict = field(compare=False)
    fitted: np.ndarray | None = field(default=None, compare=False)  # (nx, ny) bool; None: a version 1 file


def read_surface_file(path: str | Path) -> RawSurface:
    """The arrays and metadata of a surface file of this format (version 1 or 2), read bounded; ValueError
    (one line) for a file that cannot be read, is damaged or foreign, or is of another version."""
    path = Path(path)
    try:
        data = read_bounded(path, MAX_SURFACE_BYTES, "surface file")
    except InputError as exc:
        raise ValueError(str(exc)) from None
    except OSError as exc:
        raise ValueError(f"cannot read surface file {path}: {exc.strerror or exc}") from None
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            if set(z.files) not in _ARRAYS.values():
                raise ValueError(f"it holds {sorted(z.files)}, not heights_m, meta (and fitted)")
            heights = np.asarray(z["heights_m"])
            fitted = np.asarray(z["fitted"]) if "fitted" in z.files else None
            meta = json.loads(str(z["meta"]))
    except Exception as exc:  # zip, npy and JSON errors come in many types; all mean a damaged or foreign file
        raise ValueError(f"{path} is not a pilescan surface file ({type(exc).__name__}: {exc})"[:300]) from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        fmt = meta.get("format") if isinstance(meta, dict) else meta
        raise ValueError(f"{path} is not a pilescan surface file (format {fmt!r})"[:300])
    version = meta.get("format_version")
    if isinstance(version, bool) or version not in READ_VERSIONS:
        raise ValueError(f"{path}: surface file version {version!r} is not one of the supported "
                         f"{', '.join(map(str, READ_VERSIONS))}"[:300])
    if (fitted is not None) != (version >= 2):
        raise ValueError(f"{path}: a version {version} surface file " + ("lacks its fitted cells' mask"
                                                                          if fitted is None else "holds a fitted mask"))
    if fitted is not None and (fitted.dtype != np.bool_ or fitted.shape != heights.shape):
        raise ValueError(f"{path}: surface file fitted mask is {fitted.dtype} {fitted.shape}, not bool "
                         f"{heights.shape} like its heights")
    return RawSurface(heights, meta, fitted)


def meta_number(meta: dict, key: str, path: str | Path, *, minimum: float = 0.0, maximum: float = math.inf) -> float:
    """meta[key] as a float, a finite number within [minimum, maximum]; ValueError (one line, naming the file and
    the field) for one missing, not a number (a string, a JSON boolean, null), NaN, infinite or out of bounds."""
    v = meta.get(key)
    x = math.nan
    if isinstance(v, int | float) and not isinstance(v, bool):
        try:
            x = float(v)
        except OverflowError:  # a JSON integer beyond a float's range: no number either
            pass
    if not (math.isfinite(x) and minimum <= x <= maximum):
        within = f">= {minimum:g}" if maximum == math.inf else f"within {minimum:g} to {maximum:g}"
        raise ValueError(f"{path}: surface file field {key} must be a finite number {within}, got {v!r}"[:300])
    return x
