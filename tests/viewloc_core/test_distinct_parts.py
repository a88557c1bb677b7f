"""Distinct parts: fits that claim the same pixels are one part."""

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from viewloc_core.camera import Camera
from viewloc_core.distinct_parts import (
    SAME_PART_CENTRE_SHARE,
    distinct_parts,
    footprint,
)
from viewloc_core.pose import Pose
from viewloc_core.shading import SurfaceSamples, surface_samples

CAMERA = Camera(600.0, 600.0, 319.5, 239.5, 640, 480)

#: A flat bar, 120 x 30 x 10 mm: long enough that two lying side by side
#: have centres much closer than the bar's diameter.
BAR_MM = (120.0, 30.0, 10.0)


@pytest.fixture(scope="module")
def bar() -> tuple[SurfaceSamples, float]:
    mesh = trimesh.creation.box(BAR_MM)
    samples = surface_samples(np.asarray(mesh.vertices), np.asarray(mesh.faces))
    return samples, float(np.linalg.norm(BAR_MM))


def _facing(t_mm: tuple[float, float, float], turn_deg: float = 0.0) -> Pose:
    """The bar lying flat, its large face to the camera, turned in the image."""
    return Pose(Rotation.from_euler("z", turn_deg, degrees=True).as_matrix(), np.array(t_mm))


def test_a_second_fit_a_little_off_is_the_same_part(bar) -> None:
    samples, diameter = bar
    fits = [_facing((0.0, 0.0, 700.0)), _facing((3.0, -2.0, 710.0), 4.0),
            _facing((0.0, 0.0, 700.0), 180.0)]
    assert distinct_parts(fits, CAMERA, diameter, samples) == [0]


def test_parts_side_by_side_are_two_though_their_centres_are_close(bar) -> None:
    # Two bars touching along their long sides: centres 32 mm apart, a
    # quarter of the diameter; the centre rule alone would merge them.
    samples, diameter = bar
    fits = [_facing((0.0, 0.0, 700.0)), _facing((0.0, 32.0, 700.0))]
    assert SAME_PART_CENTRE_SHARE * diameter > 32.0
    assert distinct_parts(fits, CAMERA, diameter, samples) == [0, 1]
    assert distinct_parts(fits, CAMERA, diameter, None) == [0]


def test_crossed_bars_overlap_too_little_to_be_one(bar) -> None:
    # Two bars crossing at right angles share the square where they cross:
    # a quarter of each footprint at most.
    samples, diameter = bar
    fits = [_facing((0.0, 0.0, 700.0)), _facing((0.0, 0.0, 690.0), 90.0)]
    assert distinct_parts(fits, CAMERA, diameter, samples) == [0, 1]


def test_without_a_mesh_the_projected_centres_decide(bar) -> None:
    _, diameter = bar
    near = _facing((10.0, 0.0, 700.0))
    far = _facing((200.0, 0.0, 700.0))
    fits = [_facing((0.0, 0.0, 700.0)), near, far]
    assert distinct_parts(fits, CAMERA, diameter, None) == [0, 2]


def test_the_limit_stops_the_search(bar) -> None:
    samples, diameter = bar
    fits = [_facing((x, 0.0, 700.0)) for x in (-200.0, 0.0, 200.0)]
    assert distinct_parts(fits, CAMERA, diameter, samples) == [0, 1, 2]
    assert distinct_parts(fits, CAMERA, diameter, samples, limit=2) == [0, 1]
    assert distinct_parts([], CAMERA, diameter, samples) == []


def test_a_part_out_of_sight_has_no_footprint(bar) -> None:
    samples, _ = bar
    behind = Pose(np.eye(3), np.array([0.0, 0.0, -700.0]))
    assert footprint(samples, CAMERA, behind, 8.0).size == 0
    assert footprint(samples, CAMERA, _facing((0.0, 0.0, 700.0)), 8.0).size > 20


@settings(max_examples=40, deadline=None)
@given(
    rotvec=st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3),
    x=st.floats(-150.0, 150.0),
    y=st.floats(-100.0, 100.0),
    z=st.floats(500.0, 1200.0),
)
def test_a_fit_and_itself_are_one_part_and_far_apart_copies_two(bar, rotvec, x, y, z) -> None:
    samples, diameter = bar
    pose = Pose(Rotation.from_rotvec(rotvec).as_matrix(), np.array([x, y, z]))
    assert distinct_parts([pose, pose], CAMERA, diameter, samples) == [0]
    # A copy a diameter and a half away across the image never overlaps it.
    shift = np.array([1.5 * diameter, 0.0, 0.0]) * (1.0 if x < 0 else -1.0)
    copy = Pose(pose.R_m2c, pose.t_m2c + shift)
    assert distinct_parts([pose, copy], CAMERA, diameter, samples) == [0, 1]
