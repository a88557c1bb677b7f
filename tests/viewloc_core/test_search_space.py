"""Search space: the image region and depth range a request may give."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from tests.viewloc_core.conftest import render_copies
from viewloc_core.camera import Camera
from viewloc_core.detection import Detection, Similarity2D
from viewloc_core.errors import InvalidInputError
from viewloc_core.localize import LocalizeOptions, localize
from viewloc_core.part_colour import propose
from viewloc_core.pose import Pose
from viewloc_core.pose_from_match import similarity_from_pose
from viewloc_core.search_space import DepthRange, ImageRegion
from viewloc_core.view_sphere import view_directions


@pytest.mark.parametrize(("args", "field"), [
    ((-1, 0, 10, 10), "options.roi"), ((0, -2, 10, 10), "options.roi"),
    ((0, 0, 0, 10), "options.roi"), ((0, 0, 10, -5), "options.roi"),
])
def test_a_region_off_the_image_grid_is_refused_naming_the_option(args, field):
    with pytest.raises(InvalidInputError) as err:
        ImageRegion(*args)
    assert err.value.field == field


def test_a_region_must_lie_inside_the_image():
    ImageRegion(600, 400, 40, 80).check_within(640, 480)
    with pytest.raises(InvalidInputError, match="outside the 640x480 image") as err:
        ImageRegion(600, 400, 41, 80).check_within(640, 480)
    assert err.value.field == "options.roi"


@pytest.mark.parametrize(("lo", "hi", "field"), [
    (0.0, 100.0, "options.depth_mm.min"), (-5.0, 100.0, "options.depth_mm.min"),
    (math.nan, 100.0, "options.depth_mm.min"), (100.0, 100.0, "options.depth_mm.max"),
    (100.0, 50.0, "options.depth_mm.max"), (100.0, math.inf, "options.depth_mm.max"),
])
def test_a_depth_range_must_be_positive_and_increasing(lo, hi, field):
    with pytest.raises(InvalidInputError) as err:
        DepthRange(lo, hi)
    assert err.value.field == field


@settings(max_examples=200, deadline=None)
@given(x=st.integers(0, 500), y=st.integers(0, 300), w=st.integers(1, 139),
       h=st.integers(1, 179), factor=st.floats(0.2, 1.0),
       u=st.floats(-10.0, 700.0), v=st.floats(-10.0, 500.0))
def test_a_pixel_is_in_the_region_on_every_level_as_on_the_full_image(x, y, w, h, factor, u, v):
    # Level pixels map as u' = (u + 0.5) * factor - 0.5 (Camera.scaled):
    # the region's edges move with them, so membership does not change.
    region = ImageRegion(x, y, w, h)
    full = bool(region.contains(np.array([[u, v]]))[0])
    level = bool(region.contains(np.array([[(u + 0.5) * factor - 0.5,
                                            (v + 0.5) * factor - 0.5]]), factor)[0])
    assert full == level
    inside = x - 0.5 <= u <= x + w - 0.5 and y - 0.5 <= v <= y + h - 0.5
    assert full == inside
    # Slack only adds points.
    assert bool(region.contains(np.array([[u, v]]), 1.0, 3.0)[0]) >= full


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), f_px=st.floats(250.0, 2000.0),
       lo=st.floats(150.0, 2000.0), span=st.floats(1.01, 3.0),
       share=st.floats(0.0, 1.0), u=st.floats(0.0, 639.0), v=st.floats(0.0, 479.0),
       factor=st.sampled_from([1.0, 0.625, 0.3125]))
def test_every_depth_in_the_range_gives_a_scale_within_its_bounds(seed, f_px, lo, span, share,
                                                                   u, v, factor):
    # The part anywhere in the image, turned anyhow, its origin at any
    # depth in the range and away from its centre: the 2D scale a training
    # view shows it at (the inverse of the 6D pose from the match, at the
    # depth of any of its features) lies within the bounds.
    rng = np.random.default_rng(seed)
    camera = Camera(f_px, f_px * rng.uniform(0.95, 1.05), 319.5 + rng.uniform(-20, 20),
                    239.5 + rng.uniform(-20, 20), 640, 480)
    diameter, f_train = rng.uniform(20.0, 300.0), 512.0
    d0 = rng.uniform(2.5, 6.0) * diameter
    offset = rng.normal(size=3)
    offset *= rng.uniform(0.0, 0.5 * diameter) / np.linalg.norm(offset)
    depth = DepthRange(lo, lo * span)
    z = depth.min_mm + share * (depth.max_mm - depth.min_mm)
    R = Rotation.random(random_state=rng).as_matrix()
    # The origin on the ray through (u, v) at depth z; the centre beside it.
    t_origin = z * np.array([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, 1.0])
    t_centre = t_origin + R @ offset
    if t_centre[2] <= 0.5 * diameter:
        return
    R_view = Rotation.random(random_state=rng).as_matrix()
    ref = rng.uniform(-0.5, 0.5) * diameter
    if not abs(ref) < min(d0, float(np.linalg.norm(t_centre))):
        return
    sim = similarity_from_pose(Pose(R, t_centre), R_view, d0, f_train, camera, ref_depth_mm=ref)
    least, greatest = depth.scale_bounds(camera, factor, d0, f_train, diameter,
                                         float(np.linalg.norm(offset)))
    assert least <= sim.scale * factor <= greatest


def test_a_depth_range_holds_the_reported_origins_depth():
    pose = Pose(np.eye(3), np.array([30.0, -20.0, 500.0]))
    det = Detection(score=0.9, log_probability=0.0, model_view=0, azimuth_deg=0.0,
                    polar_deg=0.0, similarity=Similarity2D(0.0, 0.0, 0.0, 1.0), pose=pose)
    assert DepthRange(400.0, 500.0).holds(det)
    assert not DepthRange(501.0, 900.0).holds(det)


def test_colour_proposals_are_centred_in_the_rectangle_asked_for():
    log_ratio = np.full((120, 160), -1.0, np.float32)
    log_ratio[20:40, 20:40] = 3.0  # the strongest blob, left
    log_ratio[70:90, 110:130] = 2.0  # a weaker one, right
    anywhere = propose(log_ratio, np.array([6.0, 10.0, 14.0]), 1)
    assert abs(anywhere[0].x - 29.5) < 3 and abs(anywhere[0].y - 29.5) < 3
    right = propose(log_ratio, np.array([6.0, 10.0, 14.0]), 3,
                    within=np.array([80.0, 50.0, 159.0, 119.0]))
    assert right and all(80 <= p.x <= 159 and 50 <= p.y <= 119 for p in right)
    assert abs(right[0].x - 119.5) < 3 and abs(right[0].y - 79.5) < 3


@pytest.fixture(scope="module")
def three_brackets(renderer, bracket_mesh):
    """Three L-brackets side by side at three depths, their poses and camera."""
    cam = Camera(560.0, 560.0, 319.5, 239.5, 640, 480)
    views = view_directions(1)
    rng = np.random.default_rng(5)
    poses = [Pose(Rotation.from_rotvec([0.0, 0.0, rng.uniform(0.0, 2 * np.pi)]).as_matrix()
                  @ views[int(rng.integers(len(views)))].R_m2c,
                  np.array([x, rng.uniform(-40.0, 40.0), z]))
             for x, z in ((-150.0, 560.0), (0.0, 700.0), (170.0, 860.0))]
    return render_copies(renderer, bracket_mesh, cam, poses), poses, cam


def _which_copy(det, poses, cam):
    copies_px = cam.project(np.array([p.t_m2c for p in poses]))
    gaps = np.hypot(*(copies_px - [det.similarity.x, det.similarity.y]).T)
    return int(np.argmin(gaps)) if gaps.min() < 20.0 else None


@pytest.mark.parametrize("copy", [0, 1, 2])
def test_a_region_around_one_copy_finds_that_copy(three_brackets, bracket_model, copy):
    image, poses, cam = three_brackets
    u, v = cam.project(poses[copy].t_m2c[None])[0]
    region = ImageRegion(int(u) - 60, int(v) - 50, 120, 100)
    dets = localize(bracket_model, image, cam, LocalizeOptions(roi=region)).detections
    assert len(dets) == 1
    assert _which_copy(dets[0], poses, cam) == copy
    # In the full image's frame: the pose is the copy's.
    assert abs(dets[0].pose.t_m2c[2] - poses[copy].t_m2c[2]) < 0.03 * poses[copy].t_m2c[2]


def test_no_detection_is_reported_outside_the_region(three_brackets, bracket_model):
    image, poses, cam = three_brackets
    # Below the copies: only background there.
    dets = localize(bracket_model, image, cam,
                    LocalizeOptions(max_detections=3, roi=ImageRegion(0, 400, 640, 80))).detections
    # The region holds the part's centre, the image of its bounding-box centre.
    centres = [cam.project((d.pose.R_m2c @ bracket_model.origin_offset_mm + d.pose.t_m2c)[None])[0]
               for d in dets]
    assert all(v >= 400 - 0.5 for _, v in centres)
    assert all(_which_copy(d, poses, cam) is None for d in dets)


@pytest.mark.parametrize("wanted", [1, 3])
@pytest.mark.parametrize(("lo", "hi", "copy"), [(500.0, 620.0, 0), (640.0, 760.0, 1),
                                                 (800.0, 950.0, 2)])
def test_a_depth_range_finds_the_copy_at_that_depth(three_brackets, bracket_model, lo, hi, copy,
                                                    wanted):
    # One detection wanted: a copy at another depth that fits well is no
    # answer, and the spare locations are tried.
    image, poses, cam = three_brackets
    dets = localize(bracket_model, image, cam,
                    LocalizeOptions(max_detections=wanted, depth_mm=DepthRange(lo, hi))).detections
    assert dets
    assert all(lo <= d.pose.t_m2c[2] <= hi for d in dets)
    assert [_which_copy(d, poses, cam) for d in dets][0] == copy


def test_a_region_reaching_outside_the_image_is_refused(three_brackets, bracket_model):
    image, _, cam = three_brackets
    with pytest.raises(InvalidInputError) as err:
        localize(bracket_model, image, cam, LocalizeOptions(roi=ImageRegion(600, 0, 100, 10)))
    assert err.value.field == "options.roi"
