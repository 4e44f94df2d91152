"""The LAS export, read back by laspy: every usable point, its class, time, range, servo angle and flags, in W
and (with a site) in UTM with a WKT CRS."""

import laspy
import numpy as np
import pytest
from rasterio.warp import transform

from firmware_py.core.frames import StorageFrame
from firmware_py.core.geodesy import ned_to_wgs84
from firmware_py.core.samplelog import EXCLUDE_FROM_CLOUD
from firmware_py.core.storage import Storage
from ground.exports.georef import Georef
from ground.exports.las import POINT_FORMAT, PointClass, las_scale_m, point_classes, write_las
from ground.pointcloud import Cloud, SensorErrorModel, plane_tolerances_m, structure_mask
from tests.ground.exports.conftest import SITE


@pytest.fixture(scope="module")
def las_w(flown):
    return laspy.read(flown.report_dir / "cloud.las")


@pytest.fixture(scope="module")
def las_utm(flown):
    return laspy.read(flown.report_dir / "cloud_utm.las")


def test_that_every_usable_point_is_there_in_w_within_the_scale(flown, las_w):
    c = flown.survey.cloud
    assert las_w.header.version == "1.4" and las_w.header.point_format.id == POINT_FORMAT
    assert las_w.header.point_count == len(c.points_w) > len(flown.survey.pile_points_w)
    assert las_w.header.scales == pytest.approx([0.001] * 3)  # a tenth of the LIDAR-Lite's 1 cm
    xyz = np.column_stack([las_w.x, las_w.y, las_w.z])
    assert np.abs(xyz - c.points_w).max() <= 0.0005 + 1e-9
    assert las_w.header.mins == pytest.approx(c.points_w.min(axis=0), abs=0.001)
    assert las_w.header.maxs == pytest.approx(c.points_w.max(axis=0), abs=0.001)
    assert not any(isinstance(v, laspy.vlrs.known.WktCoordinateSystemVlr) for v in las_w.header.vlrs)


def test_that_time_range_servo_angle_and_flags_are_per_point(flown, las_w):
    c = flown.survey.cloud
    assert set(las_w.point_format.extra_dimension_names) == {"range", "servo_angle", "sample_flags"}
    assert np.array_equal(las_w.gps_time, c.t_s)
    assert np.allclose(las_w["range"], c.range_m, atol=1e-6)
    assert np.allclose(las_w["servo_angle"], c.servo_rad, atol=1e-6)
    assert np.allclose(las_w.scan_angle * 0.006, np.degrees(c.servo_rad), atol=0.003 + 1e-9)
    assert np.array_equal(las_w.scan_direction_flag == 1, c.sweep_dir > 0)
    assert np.array_equal(las_w["sample_flags"], c.flags)
    assert not np.any(np.asarray(las_w["sample_flags"]) & int(EXCLUDE_FROM_CLOUD))
    assert np.all(np.diff(las_w.gps_time) >= 0)  # the log's order
    assert str(las_w.header.creation_date) == flown.header["created_utc"][:10]


def test_that_walls_floor_and_pile_are_classified(flown, las_w):
    s = flown.survey
    cls = np.asarray(las_w.classification)
    counts = {PointClass(k): int(n) for k, n in zip(*np.unique(cls, return_counts=True), strict=True)}
    assert counts[PointClass.BUILDING] == int(structure_mask(s.cloud, s.storage,
                                                             SensorErrorModel.from_header(flown.header)).sum())
    assert counts[PointClass.GROUND] + counts[PointClass.STOCKPILE] == len(s.pile_points_w)  # what the surface used
    z = np.asarray(las_w.z)
    floor = cls == PointClass.GROUND
    tol = plane_tolerances_m(s.cloud, SensorErrorModel.from_header(flown.header))[:, 2]
    assert np.all(np.abs(z[floor]) <= tol[floor] + 0.0005)  # within the stated noise of the floor (and the scale)
    assert np.median(np.abs(z[floor])) < 0.01  # mostly the floor itself (the rest: the pile's toe, within the noise)
    pile = cls == PointClass.STOCKPILE
    r = np.hypot(np.asarray(las_w.x)[pile] - 15.0, np.asarray(las_w.y)[pile] - 10.0)
    assert np.percentile(r, 99) < 6.5 and z[pile].max() == pytest.approx(4.0, abs=0.1)  # the 6 m-base, 4 m cone
    lookup = next(v for v in las_w.header.vlrs if isinstance(v, laspy.vlrs.known.ClassificationLookupVlr))
    assert lookup.lookups[64] == "stockpile" and lookup.lookups[2] == "floor"


def test_that_a_hand_made_cloud_gets_each_class():
    pts = np.array([[5.0, 5.0, 0.0], [0.0, 5.0, 3.0], [5.0, 5.0, 2.0], [5.0, 5.0, -1.0], [5.0, 5.0, 10.0]])
    dirs = np.tile([0.0, 0.0, -1.0], (len(pts), 1))
    cloud = Cloud(pts, dirs, np.full(len(pts), 5.0), pts, len(pts), 0)
    got = point_classes(cloud, Storage(10, 10, 10), SensorErrorModel(range_sigma_m=0.02))
    assert got.tolist() == [2, 6, 64, 7, 6]  # floor, wall, pile, under the floor, roof


def test_that_the_utm_variant_carries_a_wkt_crs_and_the_same_points_on_earth(flown, las_utm):
    c = flown.survey.cloud
    assert las_utm.header.point_count == len(c.points_w)
    assert las_utm.header.global_encoding.wkt
    wkt = next(v for v in las_utm.header.vlrs if isinstance(v, laspy.vlrs.known.WktCoordinateSystemVlr)).string
    assert "UTM zone 56S" in wkt and "MSL height" in wkt
    # Independently: a few points to NED by the frame, to lat/lon by the core's scalar mapping (the ellipsoid's),
    # to UTM by PROJ.
    idx = np.linspace(0, len(c.points_w) - 1, 25).astype(int)
    ned = StorageFrame(heading_rad=SITE.heading_rad).w_to_ned(c.points_w[idx])
    lat, lon = zip(*(ned_to_wgs84(n, e, SITE.corner.lat_deg, SITE.corner.lon_deg) for n, e, _ in ned), strict=True)
    east, north = transform("EPSG:4326", "EPSG:32756", list(lon), list(lat))
    assert np.asarray(las_utm.x)[idx] == pytest.approx(east, abs=0.002)
    assert np.asarray(las_utm.y)[idx] == pytest.approx(north, abs=0.002)
    assert np.asarray(las_utm.z)[idx] == pytest.approx(SITE.corner.alt_m + c.points_w[idx, 2], abs=0.002)
    assert np.array_equal(las_utm.classification, laspy.read(flown.report_dir / "cloud.las").classification)


def test_that_the_scale_is_a_tenth_of_the_quantum_coarsened_only_to_fit_int32():
    assert las_scale_m(0.01, 100.0) == pytest.approx(0.001)
    assert las_scale_m(0.001, 100.0) == pytest.approx(0.0001)
    assert las_scale_m(0.0, 100.0) == pytest.approx(0.001)  # no quantum stated: the LIDAR-Lite's
    assert las_scale_m(0.01, 5e6) == pytest.approx(0.01)  # 5,000 km at 1 mm would overflow int32


def test_that_an_empty_cloud_is_a_valid_empty_las(tmp_path, flown):
    empty = Cloud(np.empty((0, 3)), np.empty((0, 3)), np.empty(0), np.empty((0, 3)), 0, 0)
    georef, _ = Georef.from_header(flown.header)
    for g in (None, georef):
        out = write_las(empty, Storage(10, 10, 10), SensorErrorModel(), {}, tmp_path / f"{g is None}.las", g)
        assert laspy.read(out).header.point_count == 0
