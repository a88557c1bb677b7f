"""Camera intrinsics: projection, rays, distortion and validation."""

import numpy as np
import pytest

from viewloc_core.camera import Camera
from viewloc_core.errors import InvalidCameraError


def test_ray_and_projection_are_inverse():
    cam = Camera(500.0, 510.0, 319.5, 239.5, 640, 480)
    pts = np.array([[10.0, -20.0, 700.0], [-150.0, 90.0, 1000.0]])
    uv = cam.project(pts)
    rays = cam.ray(uv)
    np.testing.assert_allclose(rays, pts / np.linalg.norm(pts, axis=1, keepdims=True), atol=1e-12)


def test_distortion_round_trip():
    cam = Camera(500.0, 500.0, 320.0, 240.0, 640, 480, dist=(-0.2, 0.05, 0.001, -0.001, 0.0))
    pts = np.array([[100.0, 80.0, 500.0], [-120.0, 60.0, 600.0]])
    rays = cam.ray(cam.project(pts))
    np.testing.assert_allclose(rays, pts / np.linalg.norm(pts, axis=1, keepdims=True), atol=1e-6)


def test_scaled_keeps_pixel_centres():
    cam = Camera(500.0, 500.0, 319.5, 239.5, 640, 480)
    half = cam.scaled(0.5)
    assert (half.width, half.height) == (320, 240)
    assert half.cx == pytest.approx(159.5)


@pytest.mark.parametrize("bad", [dict(fx=0.0), dict(fy=-1.0), dict(cx=float("nan"))])
def test_rejects_bad_intrinsics(bad):
    args = dict(fx=500.0, fy=500.0, cx=320.0, cy=240.0, width=640, height=480) | bad
    with pytest.raises(InvalidCameraError):
        Camera(**args)
