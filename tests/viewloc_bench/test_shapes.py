"""Benchmark objects: one definition, committed assets, sound meshes, true symmetries."""

from collections.abc import Callable

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

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


def _rotation(axis: str, deg: float) -> np.ndarray:
    return np.asarray(Rotation.from_euler(axis, deg, degrees=True).as_matrix())


def _largest_miss_mm(v: np.ndarray, T: np.ndarray) -> float:
    """How far the vertices (N, 3) moved by a 4x4 or 3x3 transform lie from the vertex set, mm."""
    R, t = (T[:3, :3], T[:3, 3]) if T.shape == (4, 4) else (T, np.zeros(3))
    d, _ = cKDTree(v).query(v @ R.T + t)
    return float(d.max())


@pytest.mark.parametrize("make", [shapes.tee, shapes.clamp, shapes.knob, shapes.hexbolt,
                                  shapes.shaft, shapes.plate])
def test_novel_and_shop_objects_are_closed_and_sized_like_the_bracket(
    make: Callable[[], shapes.Shape],
) -> None:
    shape = make()
    for p in shape.primitives:
        part = shapes.to_trimesh(shapes.Shape("part", (p,)))
        assert part.is_watertight
        assert part.volume > 0  # faces point outwards
    mesh = shapes.to_trimesh(shape)
    assert 100.0 <= shapes.diameter_mm(mesh) <= 140.0
    # Origin near the middle: no vertex farther than 0.7 diameter from it.
    assert np.linalg.norm(mesh.vertices, axis=1).max() < 0.7 * shapes.diameter_mm(mesh)


def test_tee_has_exactly_its_half_turn_about_y() -> None:
    shape = shapes.tee()
    mesh = shapes.to_trimesh(shape)
    assert np.allclose(mesh.bounds, [[-60, -21, -21], [60, 55, 21]], atol=1e-6)
    v = np.asarray(mesh.vertices)
    assert len(shape.sym_discrete) == 1 and not shape.sym_continuous
    for S in shape.sym_discrete:
        assert not np.allclose(S, np.eye(4))
        assert np.allclose(S[:3, :3] @ S[:3, :3].T, np.eye(3)) and np.linalg.det(S[:3, :3]) > 0
        assert _largest_miss_mm(v, S) < 0.5
    assert len(shape.symmetries()) == 2
    # The half turns about x and z send the branch to -y; quarter turns swap the pipes.
    for axis, deg in (("x", 180), ("z", 180), ("y", 90), ("x", 90), ("z", 90)):
        assert _largest_miss_mm(v, _rotation(axis, deg)) > 20.0


@pytest.mark.parametrize("make", [shapes.clamp, shapes.knob])
def test_clamp_and_knob_have_no_symmetry(make: Callable[[], shapes.Shape]) -> None:
    shape = make()
    assert shape.symmetries().shape == (1, 4, 4)
    v = np.asarray(shapes.to_trimesh(shape).vertices)
    assert _largest_miss_mm(v, np.eye(3)) == 0.0
    for axis in "xyz":
        for deg in (90, 180, 270):
            assert _largest_miss_mm(v, _rotation(axis, deg)) > 10.0


def test_knob_body_is_turned_and_only_the_lever_breaks_its_symmetry() -> None:
    shape = shapes.knob()
    body, lever = shape.primitives
    assert isinstance(body, shapes.TriMesh) and body.smooth
    assert isinstance(lever, shapes.Box)
    v = body.vertices
    axis = (v[:, :2].min(axis=0) + v[:, :2].max(axis=0)) / 2  # the body's axis, off the origin
    about_axis = v - np.r_[axis, 0.0]
    for deg in (45.0, 90.0, 180.0):
        # A turn about the body's own axis by a multiple of the tessellation step.
        assert _largest_miss_mm(about_axis, _rotation("z", deg)) < 1e-6
    whole = np.asarray(shapes.to_trimesh(shape).vertices) - np.r_[axis, 0.0]
    assert _largest_miss_mm(whole, _rotation("z", 180.0)) > 30.0


@pytest.mark.parametrize("make", [shapes.hexbolt, shapes.shaft, shapes.plate])
def test_shop_objects_have_their_origin_at_the_bounding_box_centre(
    make: Callable[[], shapes.Shape],
) -> None:
    assert np.allclose(shapes.to_trimesh(make()).bounds.sum(axis=0), 0.0, atol=1e-9)


def test_hexbolt_has_exactly_its_sixfold_turns_about_y() -> None:
    shape = shapes.hexbolt()
    v = np.asarray(shapes.to_trimesh(shape).vertices)
    assert len(shape.symmetries()) == 6 and not shape.sym_continuous
    for S in shape.sym_discrete:
        assert np.allclose(S[:3, :3] @ S[:3, :3].T, np.eye(3)) and np.linalg.det(S[:3, :3]) > 0
        # The shank is a 64-gon, which a sixth of a turn moves by up to 0.33 mm.
        assert _largest_miss_mm(v, S) < 0.5
    # A twelfth of a turn moves the head's corners onto its flats; any half
    # turn across the axis swaps head and shank end.
    assert _largest_miss_mm(v, _rotation("y", 30.0)) > 2.0
    for axis in "xz":
        assert _largest_miss_mm(v, _rotation(axis, 180.0)) > 5.0


def test_shaft_is_turned_about_x_and_its_steps_tell_its_ends_apart() -> None:
    shape = shapes.shaft()
    v = np.asarray(shapes.to_trimesh(shape).vertices)
    syms = shape.symmetries(step_deg=360.0 / shapes.CYLINDER_SECTIONS)
    assert len(syms) == shapes.CYLINDER_SECTIONS
    for S in syms[::5]:
        assert _largest_miss_mm(v, S) < 1e-6
    for axis in "yz":
        assert _largest_miss_mm(v, _rotation(axis, 180.0)) > 5.0


def test_plate_is_thin_and_its_holes_break_every_symmetry() -> None:
    shape = shapes.plate()
    mesh = shapes.to_trimesh(shape)
    assert np.allclose(mesh.extents, shapes.PLATE_MM)
    # Three through holes: a closed surface of genus 3.
    assert mesh.euler_number == 2 - 2 * len(shapes.PLATE_HOLES_MM)
    assert shape.symmetries().shape == (1, 4, 4)
    v = np.asarray(mesh.vertices)
    for axis in "xyz":
        assert _largest_miss_mm(v, _rotation(axis, 180.0)) > 3.0
