"""The surface file's contract (`surface.npz` in a report directory): its name, format, version and bounds,
and the checked raw read every program shares.

The ground station writes it (`ground.surface_file`: a later survey's base, `compare`) and the coverage
planner reads it (`sitl.missions.surveyed_surface`); neither imports the other, so what they both must
agree on lives here. The file holds a float64 `heights_m` grid and one JSON string `meta` (no pickles);
what each reader needs of `meta` it checks itself.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np

from firmware_py.core.safe_read import InputError, read_bounded

SURFACE_FILE = "surface.npz"
FORMAT = "pilescan-surface"
FORMAT_VERSION = 1
MAX_GRID_CELLS = 25_000_000
"""The most cells a height grid may have (a header may claim a big building with fine cells: refuse, not
MemoryError); the ground's Grid enforces it too."""
MAX_SURFACE_BYTES = 16 * MAX_GRID_CELLS + 1_000_000
"""Largest surface file read: two float64 grids of the most cells a grid allows, plus the metadata."""


def read_surface_file(path: str | Path) -> tuple[np.ndarray, dict]:
    """(heights, meta) of a surface file of this format and version, read bounded; ValueError (one line) for
    a file that cannot be read, is damaged or foreign, or is of another version."""
    path = Path(path)
    try:
        data = read_bounded(path, MAX_SURFACE_BYTES, "surface file")
    except InputError as exc:
        raise ValueError(str(exc)) from None
    except OSError as exc:
        raise ValueError(f"cannot read surface file {path}: {exc.strerror or exc}") from None
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            if set(z.files) != {"heights_m", "meta"}:
                raise ValueError(f"it holds {sorted(z.files)}, not heights_m and meta")
            heights = np.asarray(z["heights_m"])
            meta = json.loads(str(z["meta"]))
    except Exception as exc:  # zip, npy and JSON errors come in many types; all mean a damaged or foreign file
        raise ValueError(f"{path} is not a pilescan surface file ({type(exc).__name__}: {exc})"[:300]) from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        fmt = meta.get("format") if isinstance(meta, dict) else meta
        raise ValueError(f"{path} is not a pilescan surface file (format {fmt!r})"[:300])
    if meta.get("format_version") != FORMAT_VERSION:
        raise ValueError(f"{path}: surface file version {meta.get('format_version')!r} is not the supported "
                         f"{FORMAT_VERSION}"[:300])
    return heights, meta
