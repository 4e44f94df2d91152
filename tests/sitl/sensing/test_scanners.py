"""The comparison sensors of Sec. 4.5: beam patterns, firing grid, geometry and bounded chunks."""

import dataclasses
import itertools
import math
import tracemalloc

import numpy as np
import pytest

from firmware_py.core.frames import StorageFrame
from firmware_py.core.storage import Storage
from sitl.missions.rectangle import Mission
from sitl.sensing.scanners import (
    HOKUYO_UTM_30LX,
    VELODYNE_PUCK_LITE,
    ScannerSpec,
    beam_dirs_body,
    fire_times,
    max_beams_per_chunk,
    scan_flight,
)
from sitl.vehicle.ideal_plant import IdealPlant, Trajectory
from sitl.world.raycast import World
from sitl.world.stockpile import paper_pile

SPECS = [HOKUYO_UTM_30LX, VELODYNE_PUCK_LITE]
LEVER = (0.05, -0.02, 0.10)


def hover(frame: StorageFrame, p_w, yaw_rad: float):
    """trajectory_at of a vehicle hovering level at p_w (in W)."""
    p_ned = frame.w_to_ned(np.asarray(p_w, dtype=float))

    def at(t_s: np.ndarray) -> Trajectory:
        n = len(t_s)
        z = np.zeros(n)
        return Trajectory(np.asarray(t_s, dtype=float), np.tile(p_ned, (n, 1)), z, z.copy(), np.full(n, yaw_rad))
    return at


def scan_angles_deg(d: np.ndarray) -> np.ndarray:
    """phi: in the body y-z plane, 0 straight down, + to starboard."""
    return np.degrees(np.arctan2(d[:, 1], d[:, 2]))


@pytest.mark.parametrize(("spec", "per_s"), [(HOKUYO_UTM_30LX, 40 * 1081), (VELODYNE_PUCK_LITE, 16 * 1800 * 10)])
def test_that_points_per_second_match_the_datasheets(spec, per_s):
    for t0 in (0.0, 7.3):
        assert len(fire_times(spec, t0, t0 + 1.0)) == per_s == spec.points_per_s
    paper = 43_200 if spec is HOKUYO_UTM_30LX else 288_000  # the paper's 40 x 1080, and 16 x 1800 x 10
    assert per_s == pytest.approx(paper, rel=1e-3)


def test_that_the_2d_beams_lie_in_the_body_y_z_plane_and_cover_exactly_135_deg_each_side():
    spec = HOKUYO_UTM_30LX
    t = fire_times(spec, 0.0, 1.0 / spec.rotation_hz)  # one scan
    d = beam_dirs_body(spec, t)
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    assert np.all(d[:, 0] == 0.0)
    phi = scan_angles_deg(d)
    assert len(phi) == 1081
    assert phi.min() == pytest.approx(-135.0, abs=1e-9) and phi.max() == pytest.approx(135.0, abs=1e-9)
    assert np.allclose(np.diff(phi), 0.25)  # port to starboard, one step at a time
    assert phi[540] == pytest.approx(0.0, abs=1e-9)  # the sector's centre points straight down
    # the blind 90 deg is the roof's: nothing fired more than 45 deg above the horizon
    assert np.all(-d[:, 2] <= math.sin(math.radians(45)) + 1e-12)


@pytest.mark.parametrize("t0", [0.0, 0.05, 3.33])
def test_that_the_3d_fans_16_channels_over_15_deg_and_covers_every_azimuth_once_per_revolution(t0):
    spec = VELODYNE_PUCK_LITE
    d = beam_dirs_body(spec, fire_times(spec, t0, t0 + 1.0 / spec.rotation_hz))
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    elev = np.degrees(np.arcsin(d[:, 0]))
    channel = np.rint((elev + 15.0) / 2.0).astype(int)
    assert np.allclose(elev, -15.0 + 2.0 * channel, atol=1e-9)
    assert set(channel) == set(range(16))
    steps = scan_angles_deg(d) / 0.2
    assert np.allclose(steps, np.rint(steps), atol=1e-6)  # on the 0.2 deg azimuth grid
    az = np.rint(steps).astype(int) % 1800
    pairs = az * 16 + channel
    assert len(pairs) == 28_800 and len(np.unique(pairs)) == 28_800  # each (azimuth, channel) once


@pytest.mark.parametrize("spec", SPECS)
def test_that_chunked_firing_times_neither_double_count_nor_skip(spec):
    assert np.array_equal(np.concatenate([fire_times(spec, 0, 1), fire_times(spec, 1, 2)]), fire_times(spec, 0, 2))
    edges = np.concatenate([[0.0], np.sort(np.random.default_rng(3).uniform(0, 0.3, 40)), [0.3]])
    parts = [fire_times(spec, a, b) for a, b in itertools.pairwise(edges)]
    assert np.array_equal(np.concatenate(parts), fire_times(spec, 0.0, 0.3))
    t = fire_times(spec, 0.0, 0.3)
    assert np.all(np.diff(t) > 0)


@pytest.mark.parametrize("spec", SPECS)
@pytest.mark.parametrize("frame", [StorageFrame(), StorageFrame((12.0, -7.0, 0.3), math.radians(-50))])
def test_that_hovering_in_an_empty_building_every_return_lies_on_floor_walls_or_roof(spec, frame):
    storage = Storage(60.0, 40.0, 15.0)
    world = World(storage, None, max_range_m=spec.max_range_m)
    at = hover(frame, (21.0, 17.0, 12.0), yaw_rad=0.4)
    chunks = list(scan_flight(at, 0.1, spec, world, LEVER, frame, chunk_s=0.03))
    p = np.vstack([c.points_w for c in chunks])
    dist = np.stack([p[:, 0], storage.length_m - p[:, 0], p[:, 1], storage.width_m - p[:, 1], p[:, 2],
                     storage.height_m - p[:, 2]])
    assert np.all(dist > -1e-3)  # inside the box
    assert np.all(np.abs(dist).min(axis=0) < 1e-3)  # and on one of its planes
    # The ranges are the distances from the sensor (the lever arm from the vehicle, yawed 0.4 rad).
    yaw_w = frame.heading_rad - 0.4  # the nose's direction in W, from x towards y
    c, s = math.cos(yaw_w), math.sin(yaw_w)
    sensor = np.array([21.0 + c * LEVER[0] + s * LEVER[1], 17.0 + s * LEVER[0] - c * LEVER[1], 12.0 - LEVER[2]])
    r = np.concatenate([c.range_m for c in chunks])
    assert np.allclose(np.linalg.norm(p - sensor, axis=1), r, atol=1e-3)
    assert np.all(r <= spec.max_range_m)
    assert sum(c.n_beams for c in chunks) == len(fire_times(spec, 0.0, 0.1))
    if spec is VELODYNE_PUCK_LITE:  # 100 m reaches everything: no beam lost
        assert len(r) == sum(c.n_beams for c in chunks)


@pytest.fixture(scope="module")
def pile_world():
    mission = Mission(p_traj=0.2)
    frame = StorageFrame((3.0, 4.0, 0.0), math.radians(20))
    return IdealPlant(mission, frame), World(mission.storage, paper_pile("1")), frame


@pytest.mark.parametrize("spec", SPECS)
def test_that_chunked_scanning_gives_exactly_the_points_of_one_chunk(spec, pile_world):
    plant, world, frame = pile_world
    t0 = 20.0  # mid-leg, over the pile
    at = lambda t: plant.states(t + t0)  # noqa: E731
    one = list(scan_flight(at, 0.25, spec, world, LEVER, frame, chunk_s=1.0))
    many = list(scan_flight(at, 0.25, spec, world, LEVER, frame, chunk_s=0.013))
    assert len(one) == 1 and len(many) == math.ceil(0.25 / 0.013)
    for k in ("points_w", "range_m", "dirs_w", "t_s"):
        assert np.array_equal(getattr(one[0], k), np.concatenate([getattr(c, k) for c in many]))
    assert one[0].n_beams == sum(c.n_beams for c in many)
    assert np.array_equal(one[0].path_w, np.vstack([c.path_w for c in many]))


def test_that_noise_is_off_by_default_and_seeded_when_asked(pile_world):
    plant, world, frame = pile_world
    spec = HOKUYO_UTM_30LX
    ideal = np.concatenate([c.range_m for c in scan_flight(plant.states, 1.0, spec, world, LEVER, frame)])
    noisy = [np.concatenate([c.range_m for c in scan_flight(plant.states, 1.0, spec, world, LEVER, frame,
                                                             rng=np.random.default_rng(7))]) for _ in range(2)]
    assert np.array_equal(noisy[0], noisy[1])
    assert np.std(noisy[0] - ideal) == pytest.approx(spec.range_sigma_m, rel=0.03)


def test_that_a_chunk_never_exceeds_its_bound_and_memory_does_not_grow_with_the_flight(pile_world):
    plant, world, frame = pile_world
    spec = VELODYNE_PUCK_LITE
    chunk_s, duration_s = 0.02, 1.0
    bound = max_beams_per_chunk(spec, chunk_s)
    n_total = 0
    tracemalloc.start()
    try:
        for c in scan_flight(plant.states, duration_s, spec, world, LEVER, frame, chunk_s=chunk_s):
            assert len(c) <= c.n_beams <= bound
            assert c.points_w.shape == (len(c), 3) and c.dirs_w.shape == (len(c), 3)
            n_total += c.n_beams
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert n_total == 288_000
    held = n_total * 8 * 8  # what the flight's points, directions, ranges and times would take at once
    assert peak < held / 4, f"peak {peak / 1e6:.1f} MB for a flight of {held / 1e6:.1f} MB"


def test_that_a_spec_refuses_a_step_that_does_not_divide_the_circle():
    with pytest.raises(ValueError, match="divide"):
        dataclasses.replace(HOKUYO_UTM_30LX, step_deg=0.7)
    with pytest.raises(ValueError, match="elevation"):
        ScannerSpec("x", 0.1, 10.0, 0.01, 10.0, 1.0, 360.0, channel_elevations_deg=(95.0,))
