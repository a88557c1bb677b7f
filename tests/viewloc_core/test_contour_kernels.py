"""The refinement's compiled inner steps against their array formulation."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from viewloc_core.camera import Camera
from viewloc_core.contour_kernels import edge_residuals, project_contour
from viewloc_core.normal_search import search_normals


def _array_projection(points, normals, R, t, camera, lo, hi):
    """The array formulation refine._Projector.project used before it was compiled."""
    X = points @ R.T + t
    front = X[:, 2] > 1.0
    X, turned = X[front], (normals @ R.T)[front]
    step = turned * (X[:, 2] / camera.focal_px)[:, None] + X
    uv = camera.project(X)
    d = camera.project(step) - uv
    norm = np.hypot(d[:, 0], d[:, 1])
    ok = (uv >= lo).all(axis=1) & (uv <= hi).all(axis=1) & (norm > 1e-6)
    return uv[ok], d[ok] / norm[ok, None], X[ok], np.flatnonzero(front)[ok]


def _array_residuals(grad, uv, n2, X, t, camera, level, search, prior):
    """The array formulation refine._matches used before it was compiled."""
    f = 2.0**level
    uv_l = (uv + 0.5) / f - 0.5 if level else uv
    found, offset = search_normals(grad, np.ascontiguousarray(uv_l), n2, search, 0.02,
                                   math.cos(math.radians(35.0)), prior)
    n2, X, r = n2[found], X[found], -offset[found] * f
    x, y, z = X[:, 0], X[:, 1], X[:, 2]
    a = n2[:, 0] * camera.fx / z
    b = n2[:, 1] * camera.fy / z
    c = -(a * x + b * y) / z
    px, py, pz = x - t[0], y - t[1], z - t[2]
    return np.column_stack([py * c - pz * b, pz * a - px * c, px * b - py * a, a, b, c]), r


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.booleans(), st.integers(0, 1))
def test_compiled_steps_equal_the_array_formulation(seed, distorted, level):
    rng = np.random.default_rng(seed)
    dist = (-0.2, 0.05, 0.001, -0.002, 0.0) if distorted else ()
    camera = Camera(fx=600.0, fy=590.0, cx=320.0, cy=240.0, width=640, height=480, dist=dist)
    points = rng.uniform(-40.0, 40.0, (150, 3))
    normals = rng.normal(size=(150, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    R = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    # Far enough that most points are in the image, near enough that some
    # leave it (and, at times, pass behind the camera).
    t = np.array([rng.uniform(-150, 150), rng.uniform(-100, 100), rng.uniform(20, 400)])
    margin = 1.0
    lo = np.array([margin, margin])
    hi = np.array([camera.width - 1 - margin, camera.height - 1 - margin])
    window = np.concatenate([0.5 * (lo + hi), 0.5 * (hi - lo)])
    intrinsics = np.array([camera.fx, camera.fy, camera.cx, camera.cy, camera.focal_px])
    coefficients = np.zeros(8)
    coefficients[:len(dist)] = dist
    uv, n2, X, index = project_contour(points, normals, R, t, intrinsics, coefficients,
                                       distorted, window)
    want_uv, want_n2, want_X, want_index = _array_projection(points, normals, R, t, camera,
                                                              lo, hi)
    np.testing.assert_allclose(uv, want_uv, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(n2, want_n2, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(X, want_X, rtol=1e-12, atol=1e-9)
    np.testing.assert_array_equal(index, want_index)

    size = (camera.height >> level, camera.width >> level)
    grad = rng.normal(0.0, 0.05, (*size, 2)).astype(np.float32)
    prior = np.exp(-0.5 * (np.arange(-4, 5) / 2.0) ** 2)
    J, r = edge_residuals(grad, uv, n2, X, t, camera.fx, camera.fy, level, 5, 0.02,
                          math.cos(math.radians(35.0)), prior)
    want_J, want_r = _array_residuals(grad, uv, n2, X, t, camera, level, 5, prior)
    np.testing.assert_allclose(r, want_r, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(J, want_J, rtol=1e-12, atol=1e-9)


def test_points_behind_the_camera_or_outside_the_window_are_dropped():
    points = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -150.0], [500.0, 0.0, 0.0]])
    normals = np.tile([1.0, 0.0, 0.0], (3, 1))
    uv, n2, X, index = project_contour(
        points, normals, np.eye(3), np.array([0.0, 0.0, 100.0]),
        np.array([500.0, 500.0, 320.0, 240.0, 500.0]), np.zeros(8), False,
        np.array([319.5, 239.5, 318.5, 238.5]))
    np.testing.assert_allclose(uv, [[320.0, 240.0]])
    np.testing.assert_allclose(n2, [[1.0, 0.0]])
    np.testing.assert_allclose(X, [[0.0, 0.0, 100.0]])
    np.testing.assert_array_equal(index, [0])
