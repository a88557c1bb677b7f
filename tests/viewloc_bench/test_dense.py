"""The dense mesh the bench learns to time learning: same shape, colours, written once."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from viewloc_bench.dense import dense_mesh, dense_object
from viewloc_bench.sets import BenchObject
from viewloc_core.mesh import mesh_vertex_colours


def _coloured_box(path: Path) -> Path:
    box = trimesh.creation.box((40.0, 20.0, 10.0))
    rgba = np.tile(np.array([[200, 120, 40, 255]], np.uint8), (len(box.vertices), 1))
    rgba[box.vertices[:, 0] > 0] = [20, 60, 220, 255]
    box.visual = trimesh.visual.ColorVisuals(box, vertex_colors=rgba)
    path.write_bytes(box.export(file_type="ply"))
    return path


def test_the_dense_mesh_has_four_times_the_faces_per_step_and_the_same_shape(tmp_path):
    source = _coloured_box(tmp_path / "box.ply")
    out = dense_mesh(source, tmp_path / "dense", subdivisions=2)
    assert out.name == "box_x16.ply"
    dense = trimesh.load(out, force="mesh", process=False)
    box = trimesh.load(source, force="mesh", process=False)
    assert len(dense.faces) == 16 * len(box.faces)
    np.testing.assert_allclose(dense.bounds, box.bounds, atol=1e-6)
    assert abs(dense.volume - box.volume) < 1e-6
    # Colours are interpolated along the new edges: the corners keep theirs.
    colours = mesh_vertex_colours(dense)
    assert colours is not None
    corners = np.all(np.isclose(np.abs(dense.vertices), [20.0, 10.0, 5.0]), axis=1)
    assert np.all(colours[corners & (dense.vertices[:, 0] > 0)] == [20, 60, 220])
    assert np.all(colours[corners & (dense.vertices[:, 0] < 0)] == [200, 120, 40])


def test_the_dense_mesh_is_written_once(tmp_path):
    source = _coloured_box(tmp_path / "box.ply")
    first = dense_mesh(source, tmp_path / "dense", subdivisions=1)
    stamp = first.stat().st_mtime_ns
    assert dense_mesh(source, tmp_path / "dense", subdivisions=1) == first
    assert first.stat().st_mtime_ns == stamp


def test_the_dense_object_is_named_by_its_factor(tmp_path):
    source = _coloured_box(tmp_path / "box.ply")
    obj = BenchObject("box", source, 46.0, np.eye(4)[None], np.zeros((1, 3)))
    dense, faces = dense_object(obj, tmp_path / "dense", subdivisions=1)
    assert dense.name == "box-x4" and faces == 48
    assert dense.mesh_path.parent == tmp_path / "dense"
    assert dense.diameter_mm == obj.diameter_mm
