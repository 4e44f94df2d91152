"""What `--export` accepts, the files each format writes, and the one-line error for a missing library."""

from __future__ import annotations

import enum
import importlib
from types import ModuleType

from firmware_py.core.cli import UserError

EXTRA = "ground"
"""The pyproject extra that installs every export library (`pip install 'pilescan[ground]'`)."""


class ExportFormat(enum.Enum):
    """One --export name; its value is what the user types."""

    LAS = "las"
    TIF = "tif"
    MESH = "mesh"
    CONTOURS = "contours"


ALL = "all"
"""--export all: every format."""

FILES: dict[ExportFormat, tuple[str, ...]] = {
    ExportFormat.LAS: ("cloud.las", "cloud_utm.las"),
    ExportFormat.TIF: ("surface.tif",),
    ExportFormat.MESH: ("surface.ply",),
    ExportFormat.CONTOURS: ("contours.geojson", "contours_wgs84.geojson"),
}
"""Every file a format may write (the *_utm / *_wgs84 ones only when the log header has a site)."""

EXPORT_FILES: tuple[str, ...] = tuple(name for names in FILES.values() for name in names)
"""Every file the exports may put in a report directory (what --force removes)."""

LIBRARIES: dict[ExportFormat, tuple[str, ...]] = {
    ExportFormat.LAS: ("laspy",),
    ExportFormat.TIF: ("rasterio",),
    ExportFormat.MESH: ("matplotlib",),  # its colour maps; the PLY is written here
    ExportFormat.CONTOURS: ("contourpy",),
}
GEOREFERENCED_LIBRARIES: dict[ExportFormat, tuple[str, ...]] = {ExportFormat.LAS: ("rasterio",)}
"""More a format needs when the log header has a site: the LAS's UTM variant projects with PROJ (rasterio's)."""


def parse_formats(text: str | None) -> tuple[ExportFormat, ...]:
    """'las,tif' -> (LAS, TIF) in the order given, duplicates dropped; 'all' -> every format; '' or None ->
    none. UserError naming the unknown name and the known ones."""
    if text is None or not text.strip():
        return ()
    names = [n.strip().lower() for n in text.split(",")]
    if any(not n for n in names):
        raise UserError(f"--export {text!r} has an empty name: give a comma list of "
                        f"{', '.join(f.value for f in ExportFormat)} or {ALL}")
    if ALL in names:
        return tuple(ExportFormat)
    known = {f.value: f for f in ExportFormat}
    bad = [n for n in names if n not in known]
    if bad:
        raise UserError(f"--export: unknown format {bad[0]!r}; known: {', '.join(known)}, or {ALL}")
    return tuple(dict.fromkeys(known[n] for n in names))


def need(module: str, fmt: ExportFormat) -> ModuleType:
    """Import an optional library, or a UserError naming the extra that installs it."""
    try:
        return importlib.import_module(module)
    except ImportError:
        raise UserError(f"--export {fmt.value} needs the Python package {module!r}, which is not installed: "
                        f"pip install 'pilescan[{EXTRA}]'") from None


def check_libraries(formats: tuple[ExportFormat, ...], georeferenced: bool) -> None:
    """Every library the formats need (more when georeferenced), imported up front: a missing one is refused
    before the long part."""
    for fmt in formats:
        for module in LIBRARIES[fmt] + (GEOREFERENCED_LIBRARIES.get(fmt, ()) if georeferenced else ()):
            need(module, fmt)
