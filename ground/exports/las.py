"""The survey's points as LAS 1.4 (point format 6), read by CloudCompare, QGIS, PDAL, LAStools, laspy.

Every usable point goes in (walls, roof and floor too, not just the pile), classified (ASPRS codes, with a
Classification Lookup VLR naming them):

- 2 ground: the floor, points within their sensor tolerance of z = 0 (`ground.pointcloud.plane_tolerances_m`,
  the tolerance the wall and roof removal uses);
- 6 building: walls and roof (`ground.pointcloud.structure_mask`);
- 7 low point (noise): below the floor by more than that tolerance, which no beam can see (a glitch);
- 64 stockpile (ASPRS leaves 64-255 to users): the rest, the points the surface was fitted to.

Per point: ``gps_time`` is the sample's time on the log's own clock (the payload's companion clock, seconds:
not GPS time, and the header's global encoding leaves the time type at "GPS week time", the one that claims
no absolute epoch); ``scan_angle`` is the servo angle (LAS's own convention: 0 at nadir, positive to the right
of the flight direction, as the servo's; in 0.006 deg steps) and ``scan_direction_flag`` its sweep direction
(1: sweeping to starboard); the extra dimensions keep what LAS has no field for, at full precision:
``range`` (m), ``servo_angle`` (rad), ``sample_flags`` (`firmware_py.core.samplelog.SampleFlags`).

Coordinates: ``cloud.las`` is in the storage frame W (metres, x along the length, y along the width, z up
from the floor corner; no CRS: W is the building's own engineering frame), offset 0 so a reader's numbers
are W's. With a site in the log header, ``cloud_utm.las`` holds the same points in UTM easting/northing and
altitude above mean sea level (`ground.exports.georef`) with a WKT CRS VLR (LAS 1.4's way; GeoTIFF keys are
for the legacy formats 0-5), offset by the whole metres of the points' minimum.

Scale: a tenth of the sensor's range quantum (header ``sensor.resolution_m``) rounded down to a power of ten:
1 mm for the LIDAR-Lite's 1 cm, so storing adds at most 0.5 mm, 5 % of the quantum, to errors of centimetres.
LAS stores int32 counts of the scale, so the scale is coarsened tenfold while the farthest point from the
offset would not fit: at 1 mm that is 2,147 km, which no building reaches.
"""

from __future__ import annotations

import enum
import math
from datetime import datetime
from pathlib import Path

import numpy as np

from firmware_py.core.storage import Storage
from firmware_py.core.version import software_version
from ground.exports.formats import ExportFormat, need
from ground.exports.georef import Georef
from ground.pointcloud import Cloud, SensorErrorModel, plane_tolerances_m, structure_mask

POINT_FORMAT = 6
"""LAS 1.4's base format: GPS time, 8-bit classes (room for user classes >= 64), WKT CRS."""
INT32_MAX = 2**31 - 1
SCAN_ANGLE_STEP_DEG = 0.006
"""LAS 1.4 point formats 6-10 store the scan angle in 0.006 deg steps (+-30,000 = +-180 deg)."""
FALLBACK_QUANTUM_M = 0.01
"""A header that states no range quantum (resolution 0) gets this: the LIDAR-Lite v3's and the TFMini's."""


class PointClass(enum.IntEnum):
    """ASPRS classification codes written (module docstring)."""

    GROUND = 2
    BUILDING = 6
    LOW_NOISE = 7
    STOCKPILE = 64


CLASS_NAMES = {PointClass.GROUND: "floor", PointClass.BUILDING: "wall or roof", PointClass.LOW_NOISE: "below floor",
               PointClass.STOCKPILE: "stockpile"}
"""The Classification Lookup VLR's names (15 ASCII characters at most)."""

EXTRA_DIMS = (("range", np.float32, "range, m"), ("servo_angle", np.float32, "servo angle, rad"),
              ("sample_flags", np.uint16, "pilescan SampleFlags"))
"""The extra dimensions: name, type, description (LAS limits descriptions to 32 characters)."""


def point_classes(cloud: Cloud, storage: Storage, err: SensorErrorModel) -> np.ndarray:
    """(N,) uint8 ASPRS class of each point of the cloud (module docstring)."""
    structure = structure_mask(cloud, storage, err)
    tol_z = plane_tolerances_m(cloud, err)[:, 2]
    z = cloud.points_w[:, 2]
    out = np.full(len(z), PointClass.STOCKPILE, dtype=np.uint8)
    out[~structure & (np.abs(z) <= tol_z)] = PointClass.GROUND
    out[structure] = PointClass.BUILDING
    out[z < -tol_z] = PointClass.LOW_NOISE
    return out


def las_scale_m(quantum_m: float, max_abs_m: float) -> float:
    """The coordinate scale (module docstring): a power of ten at most a tenth of the quantum, coarsened
    until max_abs_m (the farthest coordinate from the offset) fits LAS's int32."""
    q = quantum_m if math.isfinite(quantum_m) and quantum_m > 0 else FALLBACK_QUANTUM_M
    scale = 10.0 ** math.floor(math.log10(q / 10.0) + 1e-9)
    while max_abs_m / scale > INT32_MAX / 2:  # half: rounding and the readers' own arithmetic keep headroom
        scale *= 10.0
    return scale


def write_las(cloud: Cloud, storage: Storage, err: SensorErrorModel, header: dict, out: Path,
              georef: Georef | None = None) -> Path:
    """Write the cloud as LAS 1.4 to out: in W, or with georef in UTM (module docstring)."""
    laspy = need("laspy", ExportFormat.LAS)
    from laspy.vlrs.known import ClassificationLookupVlr, WktCoordinateSystemVlr

    p = np.asarray(cloud.points_w, dtype=float).reshape(-1, 3)
    n = len(p)
    if georef is None:
        coords = p
        offsets = np.zeros(3)
    else:
        coords = np.column_stack(georef.w_to_utm(p)) if n else np.empty((0, 3))
        offsets = np.floor(coords.min(axis=0)) if n else np.zeros(3)
    max_abs = float(np.abs(coords - offsets).max()) if n else 0.0
    scale = las_scale_m(err.resolution_m, max_abs)

    hdr = laspy.LasHeader(version="1.4", point_format=POINT_FORMAT)
    hdr.add_extra_dims([laspy.ExtraBytesParams(name, dtype, desc) for name, dtype, desc in EXTRA_DIMS])
    hdr.offsets = offsets
    hdr.scales = np.full(3, scale)
    hdr.system_identifier = "pilescan drone LiDAR survey"[:32]
    hdr.generating_software = f"pilescan {software_version()}"[:32]
    created = _created_date(header)
    if created is not None:
        hdr.creation_date = created
    lookup = ClassificationLookupVlr()
    for cls, name in CLASS_NAMES.items():
        lookup[int(cls)] = name
    hdr.vlrs.append(lookup)
    if georef is not None:
        from rasterio.crs import CRS

        hdr.vlrs.append(WktCoordinateSystemVlr(CRS.from_user_input(georef.crs_text).to_wkt()))
        hdr.global_encoding.wkt = True

    las = laspy.LasData(hdr)
    las.x, las.y, las.z = coords[:, 0], coords[:, 1], coords[:, 2]
    las.return_number = np.ones(n, dtype=np.uint8)
    las.number_of_returns = np.ones(n, dtype=np.uint8)
    las.classification = point_classes(cloud, storage, err)
    las.gps_time = _per_point(cloud.t_s, n, np.float64)
    gamma = _per_point(cloud.servo_rad, n, np.float64)
    las.scan_angle = np.clip(np.round(np.degrees(gamma) / SCAN_ANGLE_STEP_DEG), -30_000, 30_000).astype(np.int16)
    sweep = _per_point(cloud.sweep_dir, n, np.int8)
    las.scan_direction_flag = (sweep > 0).astype(np.uint8)
    las["range"] = cloud.range_m.astype(np.float32)
    las["servo_angle"] = gamma.astype(np.float32)
    las["sample_flags"] = _per_point(cloud.flags, n, np.uint16)
    out.parent.mkdir(parents=True, exist_ok=True)
    las.write(str(out))
    return out


def _per_point(values: np.ndarray | None, n: int, dtype) -> np.ndarray:
    """A per-point attribute of the cloud, zeros when the cloud was built without it."""
    return np.zeros(n, dtype=dtype) if values is None else np.asarray(values).astype(dtype)


def _created_date(header: dict):
    """The log's creation date (header ``created_utc``, ISO 8601), None when absent or unreadable."""
    raw = header.get("created_utc")
    if not isinstance(raw, str):
        return None
    try:
        return datetime.fromisoformat(raw).date()
    except ValueError:
        return None
