import sys
import threading

import numpy as np
import pytest
from scipy.optimize import brentq

from firmware_py.core.storage import Storage
from sitl.world.raycast import GEOM_BUILDING, GEOM_PILE, World
from sitl.world.stockpile import Stockpile, volume_under_mesh
from tests.sitl.conftest import frustum_mesh

MM = 1e-3


def random_down_rays(n, rng, z0=12.0):
    o = np.column_stack([rng.uniform(2, 58, n), rng.uniform(2, 38, n), np.full(n, z0)])
    g = rng.uniform(-1.2, 1.2, n)
    h = rng.uniform(-np.pi, np.pi, n)
    d = np.column_stack([np.sin(g) * np.cos(h), np.sin(g) * np.sin(h), -np.cos(g)])
    return o, d


def test_that_floor_wall_and_roof_hits_match_the_planes_to_a_millimetre():
    world = World(Storage(60, 40, 15))
    rng = np.random.default_rng(0)
    o, d = random_down_rays(5000, rng)
    d[::2, 2] *= -1  # half the rays go up to the roof
    hits = world.cast(o, d, max_range_m=1e3)
    # Analytic: smallest positive t over the six planes.
    ts = []
    for axis, lo, hi in ((0, 0, 60), (1, 0, 40), (2, 0, 15)):
        with np.errstate(divide="ignore"):
            t_lo, t_hi = (lo - o[:, axis]) / d[:, axis], (hi - o[:, axis]) / d[:, axis]
        ts += [np.where(t_lo > 0, t_lo, np.inf), np.where(t_hi > 0, t_hi, np.inf)]
    expected = np.min(ts, axis=0)
    assert np.all(hits.geom_id == GEOM_BUILDING)
    assert np.max(np.abs(hits.range_m - expected)) < MM


def test_that_cone_hits_match_the_analytic_cone_to_a_millimetre():
    R, r, h, c = 12.0, 2.0, 6.0, np.array([30.0, 20.0])
    mesh = frustum_mesh(R, r, h, c, segments=4096)
    world = World(Storage(), Stockpile(mesh, volume_under_mesh(mesh), "cone"))

    def surface(xy):
        rho = np.hypot(*(xy - c).T)
        return np.clip(h * (R - rho) / (R - r), 0.0, h)

    rng = np.random.default_rng(2)
    n = 400
    o = np.column_stack([rng.uniform(20, 40, n), rng.uniform(10, 30, n), np.full(n, 12.0)])
    g, az = rng.uniform(-0.6, 0.6, n), rng.uniform(-np.pi, np.pi, n)
    d = np.column_stack([np.sin(g) * np.cos(az), np.sin(g) * np.sin(az), -np.cos(g)])
    hits = world.cast(o, d)
    ts = np.linspace(0, 20, 2001)
    for i in range(n):
        def above(t, i=i):  # the ray's height over the cone at distances t (an array, or one float)
            t = np.atleast_1d(t)
            return (o[i, 2] + t * d[i, 2]) - surface(o[i, :2] + t[:, None] * d[i, :2])
        k = np.argmax(above(ts) <= 0)
        t_exact = brentq(lambda t, f=above: f(t)[0], ts[k - 1], ts[k], xtol=1e-9)
        assert abs(hits.range_m[i] - t_exact) < MM
    assert np.mean(hits.geom_id == GEOM_PILE) > 0.5


def test_that_nothing_beyond_the_lidar_range_returns():
    world = World(Storage(60, 40, 15))
    hits = world.cast(np.array([[1.0, 20, 5], [30, 20, 5]]), np.array([[1.0, 0, 0], [1.0, 0, 0]]))
    assert np.isnan(hits.range_m[0])  # the far wall is 59 m away
    assert hits.range_m[1] == pytest.approx(30.0, abs=MM)
    assert hits.geom_id[0] == -1


def test_that_single_and_batch_queries_agree_and_directions_need_not_be_unit():
    world = World(Storage())
    o, d = random_down_rays(50, np.random.default_rng(5))
    batch = world.cast(o, d * 3.0).range_m
    single = [world.cast_one(o[i], d[i]) for i in range(50)]
    assert np.allclose(batch, single, equal_nan=True)
    hits = world.cast(o, d * 3.0)
    assert np.allclose(hits.points_w, o + d * hits.range_m[:, None], atol=MM)


def test_that_bad_queries_are_refused():
    world = World(Storage())
    with pytest.raises(ValueError):
        world.cast(np.zeros((3, 3)), np.ones((2, 3)))
    with pytest.raises(ValueError):
        World(Storage(), max_range_m=0)
    assert len(world.cast(np.zeros((0, 3)), np.zeros((0, 3))).range_m) == 0


def test_that_a_sensor_inside_the_pile_sees_nothing_and_one_above_it_sees_the_surface():
    mesh = frustum_mesh(12.0, 2.0, 6.0, np.array([30.0, 20.0]), segments=256)
    world = World(Storage(), Stockpile(mesh, volume_under_mesh(mesh), "cone"))
    inside = np.array([[30.0, 20.0, 3.0], [25.0, 20.0, 0.05]])  # under the flat top; on the floor under the flank
    outside = np.array([[30.0, 20.0, 6.5], [5.0, 5.0, 0.05], [45.0, 20.0, 1.0]])
    assert world.buried(inside).tolist() == [True, True]
    assert world.buried(outside).tolist() == [False, False, False]
    sideways = np.array([[1.0, 0.0, 0.0]] * 2)
    assert np.isnan(world.cast(inside, sideways).range_m).all()  # not the floor under the pile, not the wall
    assert np.isnan(world.cast_one(inside[1], sideways[0]))
    assert world.cast_one(outside[0], [0.0, 0.0, -1.0]) == pytest.approx(0.5, abs=MM)
    assert world.cast(outside[1:], sideways, max_range_m=100.0).range_m == pytest.approx([55.0, 15.0], abs=MM)


def test_that_two_threads_casting_one_ray_each_get_their_own_ranges():
    """`serve` casts from two threads: the device bridge's LiDAR and the pose drift's ray straight down. Each
    must get its own ray's range (the shared one-ray rows once gave the LiDAR the ray down's, as range spikes)."""
    world = World(Storage(60, 40, 15))
    rays = {"down": ((30.0, 20.0, 12.0), (0.0, 0.0, -1.0), 12.0),  # the floor
            "side": ((30.0, 20.0, 12.0), (1.0, 0.0, 0.0), 30.0)}  # the wall x = 60
    wrong = {name: 0 for name in rays}

    def cast(name: str, incidence: bool) -> None:
        o, d, want = rays[name]
        for _ in range(20_000):
            r = world.cast_one_incidence(o, d)[0] if incidence else world.cast_one(o, d)
            wrong[name] += abs(r - want) > MM

    old = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # hand the GIL over as often as it can go: every interleaving gets its chance
    try:
        threads = [threading.Thread(target=cast, args=("down", False)),
                   threading.Thread(target=cast, args=("side", True))]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        sys.setswitchinterval(old)
    assert wrong == {"down": 0, "side": 0}


def test_that_the_pile_built_from_its_vertices_and_faces_casts_as_its_triangle_list_to_the_bit():
    """The world hands Embree the pile's vertices and faces (faster to copy than a flat list of triangles): the same
    triangles in the same order, so every ray's range, triangle and normal are those of the flat list's scene."""
    from embreex import rtcore_scene as rtcs
    from embreex.mesh_construction import TriangleMesh

    from sitl.world.raycast import building_triangles
    from sitl.world.stockpile import paper_pile

    storage = Storage(60, 40, 15)
    pile = paper_pile("2", storage)
    world = World(storage, pile)
    flat = rtcs.EmbreeScene()
    TriangleMesh(flat, building_triangles(storage).astype(np.float32))
    TriangleMesh(flat, np.ascontiguousarray(pile.mesh.triangles, dtype=np.float32))
    o, d = random_down_rays(20000, np.random.default_rng(5))
    o32, d32 = o.astype(np.float32), d.astype(np.float32)
    ours, theirs = world._scene.run(o32, d32, output=1), flat.run(o32, d32, output=1)
    assert np.count_nonzero(theirs["geomID"] == GEOM_PILE) > 10000
    for key in ("tfar", "primID", "geomID", "Ng", "u", "v"):
        assert np.array_equal(ours[key], theirs[key]), key


def test_that_the_ground_below_is_the_pile_where_it_stands_and_the_floor_elsewhere():
    import trimesh

    box = trimesh.creation.box(extents=(2.0, 2.0, 3.0))
    box.apply_translation((5.0, 5.0, 1.5))  # 3 m high over x, y in [4, 6]
    storage = Storage(20.0, 12.0, 8.0)
    world = World(storage, Stockpile(box, volume_under_mesh(box), "box"))
    assert world.heights_below_m(np.array([[5.0, 5.0], [9.0, 9.0]])) == pytest.approx([3.0, 0.0], abs=1e-5)
    assert World(storage).heights_below_m(np.array([[1.0, 1.0]])) == pytest.approx([0.0], abs=1e-5)
