"""A pose of a part hidden behind another pose of it."""

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from viewloc_core.camera import Camera
from viewloc_core.hidden_fits import HIDDEN_SHARE, lies_hidden_behind, share_inside
from viewloc_core.pose import Pose
from viewloc_core.shading import SurfaceSamples, surface_samples

CAMERA = Camera(600.0, 600.0, 319.5, 239.5, 640, 480)

#: A block 120 x 80 x 40 mm (a part larger than deep, seen face on).
BLOCK_MM = (120.0, 80.0, 40.0)


@pytest.fixture(scope="module")
def block() -> SurfaceSamples:
    mesh = trimesh.creation.box(BLOCK_MM)
    return surface_samples(np.asarray(mesh.vertices), np.asarray(mesh.faces))


def _at(xy_px: tuple[float, float], depth_mm: float, turn_deg: float = 0.0) -> Pose:
    """The block face on, its centre seen at image point ``xy_px``."""
    ray = np.array([(xy_px[0] - CAMERA.cx) / CAMERA.fx, (xy_px[1] - CAMERA.cy) / CAMERA.fy, 1.0])
    return Pose(Rotation.from_euler("z", turn_deg, degrees=True).as_matrix(), ray * depth_mm)


def test_a_far_copy_inside_the_outline_is_hidden(block) -> None:
    near = _at((320.0, 240.0), 600.0)
    far = _at((330.0, 235.0), 2400.0, 30.0)
    assert share_inside(CAMERA, far, near, block) > 0.99
    assert lies_hidden_behind(CAMERA, far, near, block)
    # Not the other way round: the near one is in front, and larger.
    assert not lies_hidden_behind(CAMERA, near, far, block)


def test_another_fit_at_the_same_place_is_not_hidden(block) -> None:
    # Turned, or a little nearer or farther: the same place, not behind it.
    near = _at((320.0, 240.0), 600.0)
    assert share_inside(CAMERA, near, near, block) > 0.99
    assert not lies_hidden_behind(CAMERA, near, near, block)
    assert not lies_hidden_behind(CAMERA, _at((320.0, 240.0), 640.0, 90.0), near, block)


def test_a_far_copy_beside_the_outline_is_seen(block) -> None:
    near = _at((200.0, 240.0), 600.0)
    # The near block spans about 120 px by 80: a copy 150 px to the side
    # shows; one across its edge shows in part, less than HIDDEN_SHARE.
    assert share_inside(CAMERA, _at((350.0, 240.0), 2400.0), near, block) == 0.0
    across = _at((258.0, 240.0), 2400.0)
    assert 0.2 < share_inside(CAMERA, across, near, block) < HIDDEN_SHARE
    assert not lies_hidden_behind(CAMERA, across, near, block)


def test_a_pose_just_in_front_of_the_camera_is_drawn_within_the_image(block) -> None:
    # The block's front face 0.5 mm from the camera projects tens of
    # thousands of pixels out: its silhouette covers the whole image, and
    # is not drawn beyond it. A far copy seen in the image lies inside it;
    # one beyond the image's edge does not.
    near = Pose(np.eye(3), np.array([0.0, 0.0, 20.5]))
    assert share_inside(CAMERA, _at((320.0, 240.0), 2400.0), near, block) > 0.99
    assert share_inside(CAMERA, _at((900.0, 240.0), 2400.0), near, block) == 0.0
    # Wholly beside the image, it hides nothing in it.
    beside = _at((-2000.0, 240.0), 600.0)
    assert share_inside(CAMERA, _at((320.0, 240.0), 2400.0), beside, block) == 0.0


def test_a_pose_behind_the_camera_hides_nothing(block) -> None:
    near = _at((320.0, 240.0), 600.0)
    behind = Pose(np.eye(3), np.array([0.0, 0.0, -500.0]))
    assert share_inside(CAMERA, near, behind, block) == 0.0
    assert share_inside(CAMERA, behind, near, block) == 0.0


@settings(max_examples=40, deadline=None)
@given(x=st.floats(220.0, 420.0), y=st.floats(180.0, 300.0), turn=st.floats(0.0, 360.0),
       ratio=st.floats(3.0, 6.0))
def test_a_copy_far_enough_along_a_ray_through_the_middle_is_hidden(
        block, x: float, y: float, turn: float, ratio: float) -> None:
    # A copy 3-6 times as far, its centre within the near block's middle
    # quarter: at most a third of the block's size, all inside it.
    near = _at((x, y), 600.0, turn)
    offset = Rotation.from_euler("z", turn, degrees=True).as_matrix()[:2, :2] @ [15.0, 10.0]
    far = _at((x + offset[0], y + offset[1]), 600.0 * ratio, turn + 45.0)
    assert lies_hidden_behind(CAMERA, far, near, block)
