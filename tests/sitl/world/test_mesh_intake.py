"""Mesh intake checks what a stockpile mesh claims: one floor-standing body of material, finite, whole."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import trimesh

from firmware_py.core.storage import Storage
from sitl.world.stockpile import MAX_MESH_BODIES, load_mesh


def box(centre_xy, size=(10.0, 10.0, 4.0), z0=0.0) -> trimesh.Trimesh:
    b = trimesh.creation.box(extents=size)
    b.apply_translation((centre_xy[0], centre_xy[1], z0 + size[2] / 2))
    return b


def export(mesh: trimesh.Trimesh, path: Path, file_type: str | None = None) -> Path:
    mesh.export(path, file_type=file_type)
    return path


def test_that_two_overlapping_closed_shells_are_refused_naming_the_overlap(tmp_path):
    path = export(trimesh.util.concatenate([box((20, 20)), box((26, 20))]), tmp_path / "two.stl")
    with pytest.raises(ValueError, match=r"closed bodies 1 \(400.0 m\^3\) and 2 \(400.0 m\^3\) overlap"):
        load_mesh(path, Storage())


def test_that_crossing_shells_with_no_vertex_inside_the_other_are_refused(tmp_path):
    cross = trimesh.util.concatenate([box((30, 20), (20, 4, 3)), box((30, 20), (4, 20, 3))])
    with pytest.raises(ValueError, match="overlap"):
        load_mesh(export(cross, tmp_path / "cross.stl"), Storage())


def test_that_a_shell_inside_another_is_refused(tmp_path):
    nested = trimesh.util.concatenate([box((30, 20), (20, 20, 6)), box((30, 20), (4, 4, 2))])
    with pytest.raises(ValueError, match="overlap"):
        load_mesh(export(nested, tmp_path / "nested.stl"), Storage())


def test_that_separate_closed_shells_are_summed(tmp_path):
    two = trimesh.util.concatenate([box((10, 10)), box((40, 25), (6, 6, 2))])
    assert load_mesh(export(two, tmp_path / "two.stl"), Storage()).volume_m3 == pytest.approx(400 + 72)


def test_that_a_closed_body_floating_above_the_floor_is_refused(tmp_path):
    with pytest.raises(ValueError, match=r"floats 3\.00 m above the floor"):
        load_mesh(export(box((20, 20), z0=3.0), tmp_path / "float.stl"), Storage())


def test_that_a_body_within_the_sensor_resolution_of_the_floor_rests_on_it(tmp_path):
    assert load_mesh(export(box((20, 20), z0=0.005), tmp_path / "b.stl"), Storage()).volume_m3 == pytest.approx(400)


@pytest.mark.parametrize("suffix", ["stl", "obj"])
def test_that_nan_vertices_are_named_as_nan(tmp_path, suffix):
    b = box((20, 20))
    v = b.vertices.copy()
    v[0, 0] = np.nan
    path = export(trimesh.Trimesh(v, b.faces, process=False), tmp_path / f"nan.{suffix}")
    with pytest.raises(ValueError, match="vertices with NaN coordinates"):
        load_mesh(path, Storage())


def test_that_a_binary_stl_with_trailing_bytes_is_refused_clearly(tmp_path):
    path = export(box((20, 20)), tmp_path / "t.stl")
    with open(path, "ab") as f:
        f.write(b"\0trailing garbage")
    with pytest.raises(ValueError, match=r"declaring 12 triangles \(684 bytes\) followed by 17 trailing bytes"):
        load_mesh(path, Storage())


def test_that_a_truncated_binary_stl_is_refused_clearly(tmp_path):
    path = export(box((20, 20)), tmp_path / "t.stl")
    path.write_bytes(path.read_bytes()[:-10])
    with pytest.raises(ValueError, match="nor a complete binary STL"):
        load_mesh(path, Storage())


def test_that_an_ascii_stl_still_loads(tmp_path):
    path = export(box((20, 20)), tmp_path / "a.stl", file_type="stl_ascii")
    assert load_mesh(path, Storage()).volume_m3 == pytest.approx(400)


def test_that_a_2_gb_stl_is_refused_by_its_size_before_reading(tmp_path):
    path = tmp_path / "huge.stl"
    with open(path, "wb") as f:
        f.truncate(2 * 1024**3)  # sparse: nothing is written
    with pytest.raises(ValueError, match="2,147,483,648 bytes, more than the"):
        load_mesh(path, Storage())


def test_that_more_triangles_than_allowed_are_refused(tmp_path):
    path = export(box((20, 20)), tmp_path / "b.stl")
    with pytest.raises(ValueError, match="more than the"):
        load_mesh(path, Storage(), max_triangles=10)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_that_a_fifo_named_as_a_mesh_is_refused_without_hanging(tmp_path):
    os.mkfifo(tmp_path / "pile.stl")
    with pytest.raises(ValueError, match="not a regular file"):
        load_mesh(tmp_path / "pile.stl", Storage())


def test_that_shells_a_millimetre_apart_share_no_material_and_are_summed(tmp_path):
    side_by_side = trimesh.util.concatenate([box((20, 20)), box((30.001, 20))])
    assert load_mesh(export(side_by_side, tmp_path / "s.stl"), Storage()).volume_m3 == pytest.approx(800)


@pytest.mark.parametrize("index", [5, -1])
def test_that_a_ply_face_naming_a_vertex_it_does_not_have_is_one_line(tmp_path, index):
    """The PLY reader does not check its indices: 5 raised IndexError, -1 flew the last vertex."""
    path = tmp_path / "bad.ply"
    path.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
                    "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
                    f"1 1 0\n2 1 0\n1 2 1\n3 0 1 {index}\n")
    with pytest.raises(ValueError, match="faces naming vertices it does not have"):
        load_mesh(path, Storage())


@pytest.mark.parametrize("make", [
    lambda: trimesh.Trimesh([[1, 1, 0], [5, 1, 0], [1, 5, 2]], [[0, 1, 2], [0, 1, 2]], process=False),  # doubled
    lambda: trimesh.Trimesh([[1, 1, 1], [5, 1, 1], [1, 5, 1]], [[0, 1, 2], [0, 2, 1]], process=False),  # two-sided
])
def test_that_a_mesh_enclosing_no_volume_is_refused_not_a_true_volume_of_0(tmp_path, make):
    with pytest.raises(ValueError, match="encloses no volume"):
        load_mesh(export(make(), tmp_path / "flat.obj"), Storage())


def test_that_a_mesh_of_more_bodies_than_a_building_holds_piles_is_refused_before_the_pairwise_check(tmp_path):
    cubes = [box((1 + (i % 60) * 0.9, 1 + (i // 60) * 0.9), (0.2, 0.2, 0.2)) for i in range(MAX_MESH_BODIES + 1)]
    with pytest.raises(ValueError, match=f"{MAX_MESH_BODIES + 1} separate closed bodies"):
        load_mesh(export(trimesh.util.concatenate(cubes), tmp_path / "many.stl"), Storage())
    assert load_mesh(export(trimesh.util.concatenate(cubes[:-1]), tmp_path / "ok.stl"), Storage()).volume_m3 \
        == pytest.approx(MAX_MESH_BODIES * 0.008)
