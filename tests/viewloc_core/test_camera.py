"""Camera intrinsics: projection, rays, distortion and validation."""

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

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


@pytest.mark.parametrize("dist", [(), (-0.2, 0.05, 0.001, -0.001, 0.01),
                                  (0.1, -0.02, 0.0, 0.002, 0.0, 0.01, 0.0, 0.001)])
def test_projection_matches_opencv(dist):
    cv2 = pytest.importorskip("cv2")
    cam = Camera(500.0, 510.0, 320.0, 240.0, 640, 480, dist=dist)
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-200, 200, (50, 2)), rng.uniform(400, 900, 50)])
    ref, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), cam.K, np.asarray(dist, float))
    uv = cam.project(pts)
    assert uv.shape == (50, 2) and uv.dtype == np.float64
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-9)
    # A single point (3,) projects like a row of one.
    np.testing.assert_allclose(cam.project(pts[0]), uv[:1])


def test_scaled_keeps_pixel_centres():
    cam = Camera(500.0, 500.0, 319.5, 239.5, 640, 480)
    half = cam.scaled(0.5)
    assert (half.width, half.height) == (320, 240)
    assert half.cx == pytest.approx(159.5)


@pytest.mark.parametrize(("bad", "field"), [
    (dict(fx=0.0), "fx"), (dict(fy=-1.0), "fx"), (dict(cx=float("nan")), "cx"),
    # Beyond any pinhole lens (a focal length of 1e-10 px made the pose NaN).
    (dict(fx=1e-10, fy=1e-10), "fx"), (dict(fx=31.9), "fx"), (dict(fy=640_001.0), "fy"),
    (dict(fx=1e200, fy=1e200), "fx"),
    (dict(cx=-6401.0), "cx"), (dict(cy=1e200), "cy"),
    (dict(dist=(0.0, 0.0, 1e10, 0.0)), "dist"),
])
def test_rejects_bad_intrinsics(bad, field):
    args = dict(fx=500.0, fy=500.0, cx=320.0, cy=240.0, width=640, height=480) | bad
    with pytest.raises(InvalidCameraError) as err:
        Camera(**args)
    assert err.value.field == field


def test_accepts_the_edges_of_the_plausible_range():
    # A 170° fisheye-like focal length, a telephoto one, a crop's principal
    # point far outside the image, a strong rational-model coefficient.
    for args in (dict(fx=32.0, fy=32.0), dict(fx=640_000.0, fy=640_000.0),
                 dict(cx=-6400.0, cy=5280.0), dict(dist=(1e4, -1e4, 0.5, -0.5, 1e4))):
        Camera(**(dict(fx=500.0, fy=500.0, cx=320.0, cy=240.0, width=640, height=480) | args))


@pytest.mark.parametrize("args", [
    # OpenCV's sample calibration (left01-14), a wide-angle lens seeing
    # about 110° across, a rational model fitted to an action camera, a
    # crop's principal point outside the image.
    dict(fx=536.07, fy=536.02, cx=342.37, cy=235.54,
         dist=(-0.2656, -0.0467, 0.00183, -0.00031, 0.2523)),
    dict(fx=300.0, fy=300.0, dist=(-0.28, 0.07, 0.0, 0.0)),
    dict(fx=870.0, fy=870.0, cx=960.0, cy=540.0, width=1920, height=1080,
         dist=(26.0, 12.0, 0.0, 0.0, 0.3, 26.3, 25.0, 2.0)),
    dict(cx=-200.0, dist=(-0.2, 0.05, 0.0, 0.0)),
])
def test_calibrated_lenses_take_every_pixel_back_to_a_ray(args):
    cam = Camera(**(dict(fx=600.0, fy=600.0, cx=319.5, cy=239.5, width=640, height=480) | args))
    corners = np.array([[0.0, 0.0], [cam.width - 1.0, 0.0], [0.0, cam.height - 1.0],
                        [cam.width - 1.0, cam.height - 1.0]])
    rays = cam.ray(corners)
    np.testing.assert_allclose(cam.project(rays * 1000.0), corners, atol=0.05)


@pytest.mark.parametrize("args", [
    # Within MAX_DISTORTION_COEFFICIENT, yet a denominator of the rational
    # model reaches 0 inside the image (a projected pose became NaN: a
    # server error), or the corners lie beyond the model's widest angle.
    dict(width=384, height=288, cx=191.5, cy=143.5, dist=(1000.0,) * 8),
    dict(width=384, height=288, cx=191.5, cy=143.5, dist=(0, 0, 0, 0, 0, 1e4, 1e4, 1e4)),
    dict(width=768, height=576, fx=700.0, fy=700.0, cx=-3400.0, cy=288.0,
         dist=(-0.3, 6.0, 1.0, 3.5, 0.1, -0.4, -5.0, 1.7)),
    dict(fx=300.0, fy=300.0, dist=(-1.0, 0.0, 0.0, 0.0)),
])
def test_a_lens_model_that_leaves_pixels_without_a_ray_is_refused(args):
    with pytest.raises(InvalidCameraError) as err:
        Camera(**(dict(fx=600.0, fy=600.0, cx=319.5, cy=239.5, width=640, height=480) | args))
    assert err.value.field == "dist"
    assert "viewing ray" in err.value.message


@settings(max_examples=60, deadline=None)
@given(k1=st.floats(-1.5, 0.5), focal_sides=st.floats(0.3, 2.0))
def test_a_radial_lens_is_refused_exactly_when_its_widest_angle_misses_the_corners(k1, focal_sides):
    # r_d = r (1 + k1 r²) grows up to r = 1 / sqrt(-3 k1) when k1 < 0, where
    # it reaches (2 / 3) / sqrt(-3 k1); beyond, rays fold back. A corner at
    # a larger distorted radius has no ray.
    width, height = 640, 480
    f = focal_sides * width
    corner_radius = np.hypot(width - 1 - 319.5, height - 1 - 239.5) / f
    widest = np.inf if k1 >= 0 else (2.0 / 3.0) / np.sqrt(-3.0 * k1)
    assume(abs(corner_radius - widest) > 0.02 * widest)
    args = dict(fx=f, fy=f, cx=319.5, cy=239.5, width=width, height=height,
                dist=(k1, 0.0, 0.0, 0.0))
    if corner_radius < widest:
        Camera(**args)
    else:
        with pytest.raises(InvalidCameraError):
            Camera(**args)
