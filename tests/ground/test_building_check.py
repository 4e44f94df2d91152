"""The building's size as the sweeps measure it (ground.building_check)."""

import math

import numpy as np

from firmware_py.core.storage import Storage
from ground.building_check import (
    MIN_WALL_POINTS,
    Axis,
    check_building,
    outermost,
    size_warning,
    sweep_ids,
)

RATE_HZ = 500.0


def _box_sweeps(length_m: float, width_m: float, height_m: float, n_sweeps: int = 12, logged_offset_m=(0.0, 0.0),
                box=None):
    """Sweeps across a box building from a vehicle flying along y at x = 4 m, 7 m up: the sweep plane is x-z, so each
    sweep sees the floor and both walls x = 0 and x = L. The points are placed from a pose logged_offset_m off the
    true one (a drift: every point of a sweep moves alike). box: (x0, x1, z1) of a box standing on the floor in
    front of the wall x = L (a container's face), or None."""
    angles = np.radians(np.linspace(-85.0, 85.0, 1701))  # 0.1 deg a sample: 100 samples up the far wall
    pts, t, sweep_dir, beams = [], [], [], []
    for s in range(n_sweeps):
        vehicle = np.array([4.0, 3.0 + 0.75 * s, 7.0])
        a = angles if s % 2 == 0 else angles[::-1]
        d = np.column_stack([np.sin(a), np.zeros_like(a), -np.cos(a)])
        with np.errstate(divide="ignore"):
            hits = [np.where(d[:, 2] < 0, -vehicle[2] / d[:, 2], np.inf),
                    np.where(d[:, 0] < 0, -vehicle[0] / d[:, 0], np.inf),
                    np.where(d[:, 0] > 0, (length_m - vehicle[0]) / d[:, 0], np.inf),
                    np.where(d[:, 2] > 0, (height_m - vehicle[2]) / d[:, 2], np.inf)]
            if box is not None:
                x0, _x1, z1 = box
                r_face = np.where(d[:, 0] > 0, (x0 - vehicle[0]) / d[:, 0], np.inf)
                r_face = np.where(vehicle[2] + r_face * d[:, 2] <= z1, r_face, np.inf)
                hits.append(r_face)
        r = np.min(hits, axis=0)
        beam = d * r[:, None]
        pts.append(vehicle + np.array([*logged_offset_m, 0.0]) + beam)
        beams.append(beam)
        t.append(s * len(a) / RATE_HZ + np.arange(len(a)) / RATE_HZ)
        sweep_dir.append(np.full(len(a), 1 if s % 2 == 0 else -1))
    return np.vstack(pts), np.concatenate(t), np.concatenate(sweep_dir), np.vstack(beams)


def _check(header: Storage, **kw):
    p, t, sd, beam = _box_sweeps(30.0, 20.0, 10.0, **kw)
    return check_building(p, t, sd, beam, np.full(len(p), 0.003), header)


def test_that_each_turn_of_the_servo_and_each_gap_in_time_starts_a_sweep():
    t = np.array([0.0, 0.002, 0.004, 0.006, 0.5, 0.502])
    d = np.array([1, 1, -1, -1, -1, -1])
    assert sweep_ids(t, d, 0.002).tolist() == [0, 0, 1, 1, 2, 2]
    assert sweep_ids(np.zeros(0), np.zeros(0), 0.002).size == 0


def test_that_a_side_s_wall_is_its_outermost_group_not_a_face_in_front_of_it_nor_a_stray_beyond_it():
    wall = np.full(20, 0.01)
    face = np.full(40, 1.5)  # a column's face 1.5 m in front of the wall, more points than the wall
    stray = np.array([-0.8])  # a lone return beyond the wall (multipath)
    assert abs(outermost(np.concatenate([face, wall, stray]), 0.05) - 0.01) < 1e-12
    assert outermost(np.full(MIN_WALL_POINTS - 1, 0.0), 0.05) is None


def test_that_the_sweeps_measure_the_building_whatever_the_pose_and_say_when_the_header_is_another_size():
    right = Storage(30.0, 20.0, 10.0)
    length, width = _check(right, logged_offset_m=(0.6, -0.4))  # a drifted pose moves both walls alike
    assert length.axis is Axis.LENGTH and length.n_sweeps == 12
    assert abs(length.measured_m - 30.0) < 0.002 and not length.differs
    assert width.measured_m is None and not width.differs  # no sweep here crosses the walls y = 0 and y = W
    assert size_warning((length, width), right) is None
    wrong = Storage(30.3, 20.0, 10.0)  # a header 0.3 m long
    length, _ = _check(wrong, logged_offset_m=(0.6, -0.4))
    assert length.differs and abs(length.off_m + 0.3) < 0.002
    w = size_warning(_check(wrong), wrong)
    assert "the walls x = 0 and x = L are 30.00 m apart" in w and "the log header says 30.3 m" in w
    assert "--storage 30.00x20.00x10" in w and "about 1.0 %" in w
    # where the self-calibration could not fit the structure with any mount, the sweeps' angles are named first
    doubt = size_warning(_check(wrong), wrong, mount_doubtful=True)
    assert doubt.index("check the log header's boresight") < doubt.index("--storage 30.00x20.00x10")


def test_that_a_size_within_a_tenth_of_a_percent_or_from_too_few_sweeps_is_no_warning():
    length, _ = _check(Storage(30.02, 20.0, 10.0))  # 2 cm: real walls bow by as much
    assert abs(length.off_m + 0.02) < 0.002 and not length.differs
    length, _ = _check(Storage(30.3, 20.0, 10.0), n_sweeps=4)  # four sweeps: not a measurement
    assert length.measured_m is None and not length.differs and length.n_sweeps == 4


def test_that_a_box_standing_in_front_of_a_wall_does_not_shorten_the_building():
    # a container 2 m from the wall x = L, 3 m high: its face is steep and straight too, but the wall above it is
    # further out, and nothing stands behind a wall
    length, _ = _check(Storage(30.0, 20.0, 10.0), box=(28.0, 30.0, 3.0))
    assert abs(length.measured_m - 30.0) < 0.002 and not length.differs
    assert math.isfinite(length.std_error_m)
