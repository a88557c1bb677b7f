"""Contour model: points on the rendered outline, nearest view, array round trip."""

import math

import cv2
import numpy as np
import pytest
import trimesh

from viewloc_core.camera import Camera
from viewloc_core.contour_model import (
    KIND_CREASE,
    KIND_INNER,
    KIND_OCCLUDING,
    OUTLINE_KINDS,
    ContourModel,
    build_contour_model,
)
from viewloc_core.errors import ModelFormatError
from viewloc_core.pose import Pose
from viewloc_core.render import Renderer
from viewloc_core.view_sphere import subdivided_sphere, view_rotation


def _l_bracket() -> trimesh.Trimesh:
    base = trimesh.creation.box((100.0, 40.0, 8.0))
    base.apply_translation([0.0, 0.0, 4.0])
    wall = trimesh.creation.box((8.0, 40.0, 60.0))
    wall.apply_translation([46.0, 0.0, 38.0])
    return trimesh.util.concatenate([base, wall])


@pytest.fixture(scope="module")
def setup():
    renderer = Renderer()
    mesh = _l_bracket()
    dirs, _, _ = subdivided_sphere(1)
    model = build_contour_model(mesh, dirs, renderer, 600.0, 600.0, (320, 320), 150)
    yield mesh, model, renderer
    renderer.close()


def test_occluding_points_lie_on_rendered_depth_discontinuities(setup):
    """Outer outline and inner occluding contours (the wall in front of the base)."""
    mesh, model, renderer = setup
    assert model.n_views == 42 and np.all(model.counts > 50) and np.all(model.counts <= 150)
    cam = Camera(600.0, 600.0, 319.5, 239.5, 640, 480)
    worst = []
    for v in (0, 7, 23, 41):
        pose = Pose(view_rotation(model.directions[v]), np.array([0.0, 0.0, 600.0]))
        depth = renderer.render_depth(mesh, cam, pose).depth_mm
        far = np.where(depth > 0, depth, 1e4).astype(np.float32)
        kernel = np.ones((3, 3), np.uint8)
        jump = (cv2.dilate(far, kernel) - cv2.erode(far, kernel)) > 5.0
        vs, us = np.nonzero(jump & (depth > 0))
        boundary = np.column_stack([us, vs]).astype(float)
        pts, _ = model.view_points(v)
        occ = np.isin(model.view_kinds(v), OUTLINE_KINDS)
        uv = cam.project(pose.transform(pts[occ]))
        d = np.min(np.linalg.norm(uv[:, None, :] - boundary[None, :, :], axis=2), axis=1)
        worst.append(np.percentile(d, 80))
    # Pixel centres of the discontinuity are within a pixel of the true contour;
    # a tail of points (up to 5% at 4-7 px in some views) is off: see the report.
    assert max(worst) < 1.5


def test_normals_are_perpendicular_to_the_contour(setup):
    _, model, _ = setup
    v = 5
    R = view_rotation(model.directions[v])
    pts, nrm = model.view_points(v)
    n_cam = nrm @ R.T
    # Lifted from the view's image plane: no component along its optical axis.
    assert np.abs(n_cam[:, 2]).max() < 1e-5
    np.testing.assert_allclose(np.linalg.norm(nrm, axis=1), 1.0, atol=1e-5)


def test_nearest_view_uses_the_translation(setup):
    _, model, _ = setup
    v = 12
    R = view_rotation(model.directions[v])
    assert model.nearest_view(Pose(R, np.array([0.0, 0.0, 600.0]))) == v
    # The same rotation far to the side is seen from another direction.
    off = Pose(R, np.array([600.0, 0.0, 600.0]))
    d = -off.R_m2c.T @ off.t_m2c
    assert model.nearest_view(off) == int(np.argmax(model.directions @ d))
    assert model.nearest_view(off) != v
    angle = math.degrees(math.acos(model.directions[model.nearest_view(off)] @ model.directions[v]))
    assert angle > 20


def test_arrays_round_trip(setup):
    _, model, _ = setup
    back = ContourModel.from_arrays(model.to_arrays())
    np.testing.assert_array_equal(back.points_obj, model.points_obj)
    np.testing.assert_array_equal(back.counts, model.counts)
    assert back.image_size == model.image_size and back.d0_mm == model.d0_mm
    np.testing.assert_array_equal(back.kinds, model.kinds)
    assert '"schema_version": 2' in model.metadata_json()
    # A model stored before inner contours had a kind of their own still loads.
    old = model.to_arrays()
    old["schema_version"] = 1
    old["kinds"] = np.where(old["kinds"] == KIND_INNER, KIND_OCCLUDING, old["kinds"])
    assert not np.any(ContourModel.from_arrays(old).kinds == KIND_INNER)
    unknown = model.to_arrays()
    unknown["kinds"] = np.full_like(unknown["kinds"], 7)
    with pytest.raises(ModelFormatError, match="kind"):
        ContourModel.from_arrays(unknown)
    broken = model.to_arrays()
    broken["schema_version"] = 99
    with pytest.raises(ModelFormatError):
        ContourModel.from_arrays(broken)
    del broken["counts"]
    with pytest.raises(ModelFormatError):
        ContourModel.from_arrays(broken)


def test_the_edge_of_an_open_surface_is_outline_and_outline_only_drops_creases(setup):
    _, _, renderer = setup
    # A bent sheet (two squares at 90 deg), open at its edges, seen obliquely:
    # its free edges are outline, its bend a crease.
    verts = np.array([[0, 0, 0], [60, 0, 0], [60, 60, 0], [0, 60, 0],
                      [0, 60, 60], [60, 60, 60]], float)
    faces = np.array([[0, 1, 2], [0, 2, 3], [3, 2, 5], [3, 5, 4]])
    sheet = trimesh.Trimesh(verts - verts.mean(axis=0), faces, process=False)
    direction = np.array([[0.3, -0.5, 1.0]])
    model = build_contour_model(sheet, direction, renderer, 500.0, 500.0, (200, 200))
    kinds = model.kinds[0, :model.counts[0]]
    assert (kinds == KIND_OCCLUDING).sum() > 3 * (kinds == KIND_CREASE).sum() > 0
    outline = model.outline_only()
    assert model.crease_share() == pytest.approx((kinds == KIND_CREASE).mean())
    assert outline.crease_share() == 0.0
    pts, _ = model.view_points(0, OUTLINE_KINDS)
    assert outline.counts[0] == len(pts)
    np.testing.assert_array_equal(outline.view_points(0)[0], pts)
    assert not np.any(outline.view_kinds(0) == KIND_CREASE)


def test_inner_occluding_contours_are_told_from_the_outline(setup):
    """The wall seen in front of the base: its contour there has the part
    behind it (inner); the outline has the background behind it."""
    mesh, model, renderer = setup
    cam = Camera(600.0, 600.0, 319.5, 239.5, 640, 480)
    views_with_inner = 0
    for v in range(model.n_views):
        kinds = model.view_kinds(v)
        if np.count_nonzero(kinds == KIND_INNER) < 5:
            continue
        views_with_inner += 1
        pose = Pose(view_rotation(model.directions[v]), np.array([0.0, 0.0, 600.0]))
        background = (renderer.render_depth(mesh, cam, pose).depth_mm <= 0).astype(np.uint8)
        # Distance of each pixel to the nearest background pixel.
        to_background = cv2.distanceTransform(1 - background, cv2.DIST_L2, 3)
        pts, _ = model.view_points(v)
        uv = np.rint(cam.project(pose.transform(pts))).astype(int)
        d = to_background[uv[:, 1], uv[:, 0]]
        assert np.median(d[kinds == KIND_INNER]) > 4.0
        assert np.percentile(d[kinds == KIND_OCCLUDING], 90) <= 3.0
    assert views_with_inner >= 5
