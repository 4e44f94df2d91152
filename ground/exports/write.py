"""The exports a report asked for, written into its (staging) folder: `write_exports`."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

from firmware_py.core.storage import Storage
from ground.exports.formats import FILES, ExportFormat, check_libraries
from ground.exports.georef import Georef
from ground.exports.mesh import check_mesh_memory
from ground.pointcloud import SensorErrorModel
from ground.surface import Grid


@dataclass(frozen=True)
class Written:
    """What the exports wrote (file names, in the order written) and what they could not do, for warnings."""

    files: tuple[str, ...]
    warnings: tuple[str, ...] = ()


def check_exports(formats: tuple[ExportFormat, ...], header: dict, storage: Storage, cell_m: float,
                  max_grid_memory_bytes: int) -> None:
    """What can be refused before the survey is computed, in one line each: a missing library, a mesh too big
    for the memory allowed."""
    check_libraries(formats, georeferenced=header.get("site") is not None)
    if ExportFormat.MESH in formats:
        try:
            cells = math.prod(Grid(storage.length_m, storage.width_m, cell_m).shape)
        except ValueError:  # a cell size the survey refuses, in its own words
            cells = 0
        check_mesh_memory(cells, max_grid_memory_bytes)


def write_exports(survey, header: dict, formats: tuple[ExportFormat, ...], out_dir: Path) -> Written:
    """Write each format's files (ground.exports.formats.FILES) for the survey (`ground.report.Survey`) into
    out_dir; georeferenced variants when the log header has a usable site."""
    if not formats:
        return Written(())
    georef, why = Georef.from_header(header)
    files: list[Path] = []
    for fmt in formats:
        names = FILES[fmt]
        if fmt is ExportFormat.LAS:
            from ground.exports.las import write_las

            err = SensorErrorModel.from_header(header)
            files.append(write_las(survey.cloud, survey.storage, err, header, out_dir / names[0]))
            if georef is not None:
                files.append(write_las(survey.cloud, survey.storage, err, header, out_dir / names[1], georef))
        elif fmt is ExportFormat.TIF:
            from ground.exports.raster import write_geotiff

            files.append(write_geotiff(survey.heights, survey.grid, out_dir / names[0], georef))
        elif fmt is ExportFormat.MESH:
            from ground.exports.mesh import write_mesh

            files.append(write_mesh(survey.heights, survey.grid, out_dir / names[0]))
        elif fmt is ExportFormat.CONTOURS:
            from ground.exports.contours import write_contours

            files += write_contours(survey.heights, survey.grid, out_dir, names, georef)
    return Written(tuple(p.name for p in files), (why,) if why else ())
