"""Visual hull from masked photos: it holds the part, and its outline is the masks'."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import trimesh
from hypothesis import example, given, settings
from hypothesis import strategies as st

from viewloc_core import visual_hull as vh
from viewloc_core.camera import Camera
from viewloc_core.pose import Pose
from viewloc_core.view_sphere import view_directions

CAMERA = Camera(700.0, 700.0, 319.5, 239.5, 640, 480)
DISTANCE_MM = 450.0


def _silhouette(mesh: trimesh.Trimesh, pose: Pose, camera: Camera = CAMERA) -> np.ndarray:
    """(H, W) bool: the pixels whose centres some projected face covers."""
    uv = camera.project(pose.transform(mesh.vertices))
    mask = np.zeros((camera.height, camera.width), np.uint8)
    # Faces filled at 1/16 px (cv2's shift) so the edge follows the
    # projection, not the vertices rounded to whole pixels.
    # One face at a time: fillPoly's even-odd rule would empty overlaps.
    for face in np.rint(uv[mesh.faces] * 16).astype(np.int32):
        cv2.fillConvexPoly(mask, face, 1, lineType=cv2.LINE_8, shift=4)
    return mask > 0


def _photos(mesh: trimesh.Trimesh, level: int = 2, camera: Camera = CAMERA,
            ) -> tuple[list[np.ndarray], list[Pose]]:
    poses = [Pose(v.R_m2c, np.array([0.0, 0.0, DISTANCE_MM])) for v in view_directions(level)]
    return [_silhouette(mesh, p, camera) for p in poses], poses


def _outside_share(a: np.ndarray, b: np.ndarray) -> float:
    """Share of ``a``'s pixels more than a pixel away from ``b``'s."""
    near_b = cv2.dilate(b.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    return float((a & ~near_b).sum() / max(1, a.sum()))


@settings(max_examples=4, deadline=None)
@given(sides=st.tuples(*[st.floats(min_value=30.0, max_value=110.0)] * 3),
       angles=st.tuples(*[st.floats(min_value=-180.0, max_value=180.0)] * 3),
       shift=st.tuples(*[st.floats(min_value=-10.0, max_value=10.0)] * 3))
# A box whose hull the default quadric collapse pinched (an edge of three
# faces): the simplification now keeps a closed surface closed. Seen along
# their axes, both boxes' hulls stood 3 pixels beyond the mask (2.0 % and
# 2.1 % of the outline) until the masks that agree carved once more.
@example(sides=(90.0, 39.5, 107.0), angles=(0.0, 0.0, 0.0), shift=(0.0, 0.0, 0.0))
@example(sides=(91.0, 39.5, 107.0), angles=(0.0, 0.0, 0.0), shift=(0.0, 0.0, 0.0))
def test_the_hull_of_a_box_holds_it_and_shows_its_outline(sides, angles, shift):
    box = trimesh.creation.box(extents=sides)
    box.apply_transform(trimesh.transformations.euler_matrix(*np.radians(angles)))
    box.apply_translation(shift)
    diameter = float(np.linalg.norm(sides))
    masks, poses = _photos(box)
    hull = vh.visual_hull(masks, poses, CAMERA, diameter)
    assert hull is not None and hull.is_watertight and len(hull.faces) <= vh.HULL_MAX_FACES
    # A superset of the box, a little larger where no photo grazes a face
    # (perspective views 13° apart leave its middle a low pyramid).
    assert box.volume * 0.97 < hull.volume < box.volume * 1.35
    lo, hi = box.bounds
    step = float(np.max(hi - lo)) / vh.HULL_VOXELS
    # Its corners are rounded by about two voxels (the occupancy is
    # smoothed before the surface is taken), a turned box's extremes are corners.
    assert np.all(hull.bounds[0] < lo + 4 * step) and np.all(hull.bounds[1] > hi - 4 * step)
    assert np.all(hull.bounds[0] > lo - 0.06 * diameter)
    assert np.all(hull.bounds[1] < hi + 0.06 * diameter)
    # From each photo's viewpoint the hull's outline is the photo's mask,
    # to about a pixel (the voxels are about a third of one). Measured from
    # all 162 viewpoints of 30 random boxes, a third of them unturned: at
    # most 0.23 % of the hull's pixels lay more than a pixel outside the
    # mask, at most 0.34 % of the mask's outside the hull. Every 4th
    # viewpoint keeps the test short.
    for mask, pose in zip(masks[::4], poses[::4], strict=True):
        shown = _silhouette(hull, pose)
        assert _outside_share(shown, mask) < 0.01 and _outside_share(mask, shown) < 0.01


def test_the_hull_of_a_smooth_part_has_its_normals():
    """The shading cue reads the hull's normals: on an ellipsoid they are the
    surface's to a few degrees, not marching cubes' facets (6° and more)."""
    part = trimesh.creation.icosphere(subdivisions=5, radius=1.0)
    part.apply_scale((60.0, 40.0, 30.0))
    masks, poses = _photos(part)
    hull = vh.visual_hull(masks, poses, CAMERA, 120.0)
    assert hull is not None
    points, faces = trimesh.sample.sample_surface_even(hull, 5000, seed=0)
    # The ellipsoid's normal at the nearest point along the ray from its centre.
    radii = np.array([60.0, 40.0, 30.0])
    on_part = points / np.linalg.norm(points / radii, axis=1, keepdims=True)
    normals = on_part / radii**2
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    error_deg = np.degrees(np.arccos(np.clip(
        np.sum(hull.face_normals[faces] * normals, axis=1), -1.0, 1.0)))
    assert np.median(error_deg) < 3.0 and np.percentile(error_deg, 90) < 6.0
    assert np.median(np.linalg.norm(points - on_part, axis=1)) < 0.5


def test_a_concave_part_keeps_the_notch_the_photos_see_through():
    # An L: two slabs; the notch between their arms is seen from the side.
    arm_a = trimesh.creation.box(extents=(80.0, 20.0, 30.0))
    arm_a.apply_translation((0.0, -30.0, 0.0))
    arm_b = trimesh.creation.box(extents=(20.0, 80.0, 30.0))
    arm_b.apply_translation((-30.0, 0.0, 0.0))
    part = trimesh.util.concatenate([arm_a, arm_b])
    masks, poses = _photos(part)
    hull = vh.visual_hull(masks, poses, CAMERA, 120.0)
    assert hull is not None
    # The notch's corner (20, 20, 0) is empty, the L's own corner full,
    # and the notch is carved away: the hull is far from the L's bounding box.
    winding = _winding_number(hull, np.array([[20.0, 20.0, 0.0], [-30.0, -30.0, 0.0]]))
    assert winding[0] < 0.5 < winding[1]
    l_volume = 2 * 80.0 * 20.0 * 30.0 - 20.0 * 20.0 * 30.0
    assert 0.97 * l_volume < hull.volume < 1.3 * l_volume < 80.0 * 80.0 * 30.0


def _winding_number(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    """Generalised winding number of ``mesh`` at ``points`` (1 inside, 0 outside)."""
    tri = mesh.triangles[None] - points[:, None, None]  # (P, F, 3, 3)
    a, b, c = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
    la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
    det = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
    den = (la * lb * lc + np.einsum("pfi,pfi->pf", a, b) * lc
           + np.einsum("pfi,pfi->pf", b, c) * la + np.einsum("pfi,pfi->pf", c, a) * lb)
    return np.asarray(np.arctan2(det, den).sum(axis=1) / (2 * np.pi))


def test_too_few_masks_or_no_common_volume_give_no_hull():
    box = trimesh.creation.box(extents=(60.0, 40.0, 30.0))
    masks, poses = _photos(box)
    few: list[np.ndarray | None] = [None] * len(masks)
    for i in range(vh.MIN_HULL_VIEWS - 1):
        few[i] = masks[i]
    assert vh.visual_hull(few, poses, CAMERA, 80.0) is None
    # Empty masks: nothing survives the carving.
    empty = [np.zeros_like(m) for m in masks]
    assert vh.visual_hull(empty, poses, CAMERA, 80.0) is None


def test_photos_that_leave_a_side_unseen_give_no_hull():
    """From above only (a part on a table) the cones meet in a column through
    the table, not the part: no hull, however many photos."""
    box = trimesh.creation.box(extents=(60.0, 40.0, 30.0))
    masks, poses = _photos(box)
    above = [i for i, v in enumerate(view_directions(2)) if v.polar_deg < 80.0]
    assert len(above) >= vh.MIN_HULL_VIEWS
    assert vh.unseen_angle_deg([poses[i] for i in above]) > 90.0
    assert vh.visual_hull([masks[i] for i in above], [poses[i] for i in above], CAMERA,
                          80.0) is None
    # The icosahedron's 12 directions leave caps of 37.4° unseen, its 42 of 20.9°.
    assert vh.unseen_angle_deg(poses[:12]) == pytest.approx(37.4, abs=0.5)
    assert vh.unseen_angle_deg(poses[:42]) == pytest.approx(20.9, abs=0.5)
    assert vh.unseen_angle_deg([]) == 180.0


def test_one_photo_whose_mask_misses_part_of_the_part_is_outvoted():
    box = trimesh.creation.box(extents=(60.0, 40.0, 30.0))
    masks, poses = _photos(box)
    clean = vh.visual_hull(masks, poses, CAMERA, 80.0)
    damaged = [m.copy() for m in masks]
    damaged[7][:, : CAMERA.width // 2] = False  # half of one mask lost
    hull = vh.visual_hull(damaged, poses, CAMERA, 80.0)
    assert clean is not None and hull is not None
    assert hull.volume == pytest.approx(clean.volume, rel=0.02)


def test_a_hole_in_one_mask_bores_no_tunnel():
    box = trimesh.creation.box(extents=(60.0, 40.0, 30.0))
    masks, poses = _photos(box)
    clean = vh.visual_hull(masks, poses, CAMERA, 80.0)
    holed = [m.copy() for m in masks]
    rows, cols = np.nonzero(holed[7])
    v, u = int(rows.mean()), int(cols.mean())
    holed[7][v - 3: v + 3, u - 3: u + 3] = False  # 36 of its 7,564 pixels
    hull = vh.visual_hull(holed, poses, CAMERA, 80.0)
    assert clean is not None and hull is not None
    assert hull.volume == pytest.approx(clean.volume, rel=0.002)
    assert _winding_number(hull, np.zeros((1, 3)))[0] > 0.5


@settings(max_examples=30, deadline=None)
@given(mask=st.lists(st.lists(st.booleans(), min_size=21, max_size=21), min_size=5, max_size=5),
       uv=st.lists(st.tuples(st.floats(-2.5, 23.0), st.floats(-2.5, 7.0)), min_size=1,
                   max_size=40))
def test_an_outline_cuts_the_points_beyond_half_a_pixel(mask, uv):
    """The packed-bit test of the four pixels about a point is the
    plain one, across byte boundaries (21 columns) and the image's edges."""
    mask_hw = np.array(mask, bool)
    height, width = mask_hw.shape
    uv_px = np.array(uv, np.float64)
    # A camera that maps the point (u, v, 1) to the pixel (u, v).
    points = np.column_stack([uv_px, np.ones(len(uv_px))])
    rotation, translation = np.eye(3)[None], np.zeros((1, 3))
    near = np.zeros(len(uv_px), bool)
    for i, (u, v) in enumerate(np.floor(uv_px).astype(int)):
        block = mask_hw[max(v, 0): max(v + 2, 0), max(u, 0): max(u + 2, 0)]
        near[i] = bool(block.any())
    bits = np.packbits(mask_hw, axis=1)[None]
    cut = vh._outline_cuts(points, rotation, translation, 1.0, 1.0, 0.0, 0.0, bits, width,
                           len(points))
    np.testing.assert_array_equal(cut, ~near)
    # A mask that leaves out more than the allowed share cuts nothing.
    if (~near).sum() > 0:
        spared = vh._outline_cuts(points, rotation, translation, 1.0, 1.0, 0.0, 0.0, bits,
                                  width, int((~near).sum()) - 1)
        assert not spared.any()


def test_photos_through_a_distorting_lens_carve_the_same_hull():
    # Strong barrel distortion shrinks an off-centre part's outline by a
    # few %; the carving undoes it through the camera's own model.
    box = trimesh.creation.box(extents=(60.0, 40.0, 30.0))
    box.apply_translation((40.0, -30.0, 10.0))
    lens = Camera(700.0, 700.0, 319.5, 239.5, 640, 480, dist=(-0.8, 0.3, 0.0, 0.0, 0.0))
    masks, poses = _photos(box, camera=lens)
    hull = vh.visual_hull(masks, poses, lens, 130.0)
    ideal = vh.visual_hull(*_photos(box), CAMERA, 130.0)
    assert hull is not None and ideal is not None
    assert hull.volume == pytest.approx(ideal.volume, rel=0.03)
    np.testing.assert_allclose(hull.bounds, ideal.bounds, atol=1.0)
    # Read as if pinhole, the same masks carve another shape.
    wrong = vh.visual_hull(masks, poses, CAMERA, 130.0)
    assert wrong is None or abs(wrong.volume / ideal.volume - 1.0) > 0.05


def test_carving_split_over_points_and_masks_is_carving_at_once():
    """The hull is carved on both cores, half of the points or of the masks
    on each: the same points are kept and cut as by one call over all."""
    box = trimesh.creation.box(extents=(70.0, 40.0, 55.0))
    box.apply_transform(trimesh.transformations.euler_matrix(*np.radians((25.0, -40.0, 60.0))))
    masks, poses = _photos(box, level=1)
    packed = [vh._packed(m) for m in masks]
    mask_bits = np.stack([p[0] for p in packed])
    outline_bits = np.stack([p[1] for p in packed])
    rotations = np.stack([p.R_m2c for p in poses])
    translations = np.stack([p.t_m2c for p in poses])
    points, _ = vh._grid(np.full(3, -45.0), np.full(3, 45.0), 3.0)
    camera = (CAMERA.fx, CAMERA.fy, CAMERA.cx, CAMERA.cy)
    kept = vh._kept(points, rotations, translations, *camera, mask_bits, CAMERA.width, 1)
    at = len(points) // 3
    parts = [vh._kept(points[a:b], rotations, translations, *camera, mask_bits, CAMERA.width, 1)
             for a, b in ((0, at), (at, len(points)))]
    np.testing.assert_array_equal(np.concatenate(parts), kept)
    inside = points[kept]
    # Some masks' outlines cut their few points, some cut too many and spare them.
    max_cut = 40
    cut = vh._outline_cuts(inside, rotations, translations, *camera, outline_bits, CAMERA.width,
                           max_cut)
    views = len(masks) // 2
    split = [vh._outline_cuts(inside, rotations[a:b], translations[a:b], *camera,
                              outline_bits[a:b], CAMERA.width, max_cut)
             for a, b in ((0, views), (views, len(masks)))]
    np.testing.assert_array_equal(split[0] | split[1], cut)
    assert 0 < kept.sum() < len(points) and 0 < cut.sum() < len(inside)
