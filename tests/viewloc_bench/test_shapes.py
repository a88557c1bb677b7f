"""Benchmark objects: one definition, committed assets, sound meshes, true symmetries."""

from collections.abc import Callable

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from viewloc_bench import shapes


@pytest.mark.parametrize("name", sorted(shapes.SHAPES))
def test_committed_asset_is_the_definition(name: str) -> None:
    mesh = shapes.to_trimesh(shapes.SHAPES[name]())
    asset = trimesh.load(shapes.asset_path(name), force="mesh", process=False)
    assert isinstance(asset, trimesh.Trimesh)
    a = np.unique(np.round(np.asarray(asset.vertices), 3), axis=0)
    b = np.unique(np.round(np.asarray(mesh.vertices), 3), axis=0)
    assert a.shape == b.shape
    assert np.allclose(a, b, atol=2e-3)
    assert len(asset.faces) == len(mesh.faces)


def test_barbell_dimensions_and_symmetries() -> None:
    shape = shapes.barbell()
    mesh = shapes.to_trimesh(shape)
    assert np.allclose(mesh.bounds, [[-90, -32, -32], [90, 32, 32]], atol=1e-6)
    # The bar's end rims are the farthest points: sqrt(180^2 + 15^2).
    assert shapes.diameter_mm(mesh) == pytest.approx(np.hypot(180.0, 15.0))
    syms = shape.symmetries(step_deg=360.0 / shapes.CYLINDER_SECTIONS)
    assert len(syms) == 2 * shapes.CYLINDER_SECTIONS
    v = np.asarray(mesh.vertices)
    tree = cKDTree(v)
    for S in syms[:: 7]:
        d, _ = tree.query(v @ S[:3, :3].T + S[:3, 3])
        assert d.max() < 1e-6


@pytest.mark.parametrize("make", [shapes.bracket, shapes.freeform])
def test_hard_objects_are_closed_and_asymmetric(make: Callable[[], shapes.Shape]) -> None:
    shape = make()
    for p in shape.primitives:
        assert isinstance(p, shapes.TriMesh)
        part = trimesh.Trimesh(p.vertices, p.faces, process=True)
        assert part.is_watertight
        assert part.volume > 0  # faces point outwards
    mesh = shapes.to_trimesh(shape)
    v = np.asarray(mesh.vertices)
    tree = cKDTree(v)
    # No half turn about a principal axis and no mirror maps the vertices onto themselves.
    for T in (np.diag([-1.0, -1, 1]), np.diag([-1.0, 1, -1]), np.diag([1.0, -1, -1]),
              np.diag([-1.0, 1, 1]), np.diag([1.0, -1, 1]), np.diag([1.0, 1, -1])):
        d, _ = tree.query(v @ T.T)
        assert d.max() > 5.0
    assert shape.symmetries().shape == (1, 4, 4)


def test_clutter_shapes_are_boxes_and_rods() -> None:
    f = shapes.to_trimesh(shapes.frame(100.0, 80.0, 10.0, 8.0))
    assert np.allclose(f.extents, [100.0, 80.0, 8.0])
    assert np.allclose(shapes.to_trimesh(shapes.rod(120.0, 5.0)).extents, [120, 10, 10], atol=1e-2)
    assert "box {" in shapes.to_pov(shapes.bar(100, 10, 10), "", "")
    assert "cylinder {" in shapes.to_pov(shapes.rod(100, 5), "", "")
    assert "mesh2 {" in shapes.to_pov(shapes.freeform(), "", "")
