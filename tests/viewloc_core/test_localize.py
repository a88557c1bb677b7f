"""Localization: what a detection reports about where the object is."""

import numpy as np
import pytest

from tests.viewloc_core.conftest import render_scene
from viewloc_core.camera import Camera
from viewloc_core.localize import LocalizeOptions, localize
from viewloc_core.pose import Pose
from viewloc_core.view_sphere import view_directions


@pytest.mark.parametrize("refine", [True, False])
def test_reference_point_is_the_image_of_the_mesh_origin(
    renderer, bracket_mesh, bracket_model, refine
):
    # The bracket's mesh origin is far from its bounding-box centre, which
    # the model views are centred on: the reported (x, y) must still be
    # where the mesh origin appears, as the README defines it.
    assert np.linalg.norm(bracket_model.origin_offset_mm) > 15.0
    cam = Camera(560.0, 560.0, 319.5, 239.5, 640, 480)
    R = view_directions(1)[9].R_m2c
    pose = Pose(R, np.array([30.0, -20.0, 650.0]))
    image = render_scene(renderer, bracket_mesh, cam, pose)
    result = localize(bracket_model, image, cam, LocalizeOptions(refine=refine, min_score=0.0))
    assert result.detections
    det = result.detections[0]
    origin_px = cam.project(pose.t_m2c[None])[0]
    centre_px = cam.project((R @ bracket_model.origin_offset_mm + pose.t_m2c)[None])[0]
    assert np.hypot(*(centre_px - origin_px)) > 15.0
    err_px = np.hypot(det.similarity.x - origin_px[0], det.similarity.y - origin_px[1])
    assert err_px < (3.0 if refine else 8.0)
    # The reference point and the pose agree.
    assert np.allclose(cam.project(det.pose.t_m2c[None])[0],
                       [det.similarity.x, det.similarity.y], atol=1e-6)
