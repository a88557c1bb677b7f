"""The compiled Gauss-Newton level against the array formulation it replaced."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from viewloc_core import robust
from viewloc_core.camera import Camera
from viewloc_core.contour_kernels import edge_residuals, nearest_view
from viewloc_core.gauss_newton_kernel import (
    _solve_cholesky,
    gauss_newton_level,
    rotation_from_vector,
    tukey_weights,
)
from viewloc_core.pose import Pose, rotation_angle_deg
from viewloc_core.refine import (
    RefineOptions,
    _Projector,
    _search_prior,
    _search_priors,
    prepare_edges,
)

CAM = Camera(600.0, 600.0, 322.5, 237.5, 640, 480)


@settings(max_examples=60, deadline=None)
@given(st.tuples(*[st.floats(-3.0, 3.0)] * 3))
def test_rotation_from_vector_equals_rodrigues(w):
    want, _ = cv2.Rodrigues(np.array(w, np.float64).reshape(3, 1))
    np.testing.assert_allclose(rotation_from_vector(*w), want, atol=1e-14)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_cholesky_solve_equals_numpy(seed):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(20, 6)) * rng.uniform(0.01, 100.0, 6)
    H = A.T @ A + 1e-9 * np.eye(6)
    g = rng.normal(size=6)
    ok, x = _solve_cholesky(H, g)
    assert ok
    np.testing.assert_allclose(H @ x, g, rtol=1e-6, atol=1e-9 * np.abs(g).max())
    singular = H.copy()
    singular[3, :] = singular[:, 3] = 0.0
    assert not _solve_cholesky(singular, g)[0]


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(6, 300))
def test_tukey_weights_equal_the_array_form(seed, n):
    rng = np.random.default_rng(seed)
    r = rng.standard_t(2, n) * rng.uniform(0.1, 5.0)
    want, _ = robust.tukey_weights(r, 0.5)
    np.testing.assert_allclose(tukey_weights(r, 0.5), want, rtol=1e-12, atol=1e-15)


def test_nearest_view_equals_the_array_form(bracket_contour_scene):
    _, _, model = bracket_contour_scene
    for seed in range(50):
        R = Rotation.random(random_state=seed).as_matrix()
        t = np.random.default_rng(seed).uniform(-200, 200, 3) + [0.0, 0.0, 500.0]
        assert nearest_view(model.directions, R, t) == int(np.argmax(model.directions
                                                                     @ (-R.T @ t)))


def _array_level(edges, camera, pose, model, opts, level):
    """One level of the Gauss-Newton loop as refine_pose ran it in array form."""
    projector = _Projector(camera, model, opts.point_stride)
    search = int(opts.search_px[level])
    done = 0
    for _ in range(int(opts.iterations[level])):
        proj = projector.project(pose, margin_px=1.0)
        if proj is None:
            break
        J, r = edge_residuals(edges.gradients[level], proj.uv, proj.n2, proj.X, pose.t_m2c,
                              camera.fx, camera.fy, level, search, opts.min_gradient,
                              math.cos(math.radians(opts.max_angle_deg)),
                              _search_prior(search))
        if len(r) < 6:
            break
        w, _ = robust.tukey_weights(r, min_scale=0.5 * 2.0**level)
        if np.count_nonzero(w) < 6:
            break
        H = (J * w[:, None]).T @ J
        H.flat[::7] = H.flat[::7] * (1.0 + 1e-3) + 1e-9
        delta = -np.linalg.solve(H, (J * w[:, None]).T @ r)
        dR, _ = cv2.Rodrigues(delta[:3].reshape(3, 1))
        pose = Pose(dR @ pose.R_m2c, pose.t_m2c + delta[3:])
        done += 1
        motion = float(np.abs(J @ delta).max())
        if motion < opts.tol_px * 2.0**level or (
                math.degrees(np.linalg.norm(delta[:3])) < opts.tol_rot_deg
                and np.linalg.norm(delta[3:]) < opts.tol_trans_mm):
            break
        if level == 0:
            search = max(3, min(search, int(math.ceil(4 * robust.median(np.abs(r)) + 2))))
    return pose, done


@pytest.mark.parametrize(("seed", "stride"), [(0, 1), (6, 2), (8, 1)])
def test_a_level_equals_the_array_loop(bracket_contour_scene, seed, stride):
    renderer, prepared, model = bracket_contour_scene
    rng = np.random.default_rng(seed)
    truth = Pose(Rotation.random(random_state=seed).as_matrix(),
                 np.array([rng.uniform(-50, 50), rng.uniform(-30, 30), 600.0]))
    edges = prepare_edges(renderer.render(prepared, CAM, truth).color, 2)
    axis = rng.normal(size=3)
    start = Pose(Rotation.from_rotvec(axis / np.linalg.norm(axis) * math.radians(4.0)).as_matrix()
                 @ truth.R_m2c, truth.t_m2c * [1.0, 1.0, 1.02] + [2.5, -2.0, 0.0])
    opts = RefineOptions(point_stride=stride)
    projector = _Projector(CAM, model, stride)
    pose = start
    for level in (1, 0):
        want, want_done = _array_level(edges, CAM, pose, model, opts, level)
        search = int(opts.search_px[level])
        R, t, done, step = gauss_newton_level(
            edges.gradients[level], model.points_obj, model.normals_obj, model.counts,
            model.directions, stride, pose.R_m2c, pose.t_m2c, projector.intrinsics,
            projector.dist, projector.distorted, projector.window(1.0), level, search,
            int(opts.iterations[level]), opts.min_gradient,
            math.cos(math.radians(opts.max_angle_deg)), _search_priors(search), opts.tol_px,
            opts.tol_rot_deg, opts.tol_trans_mm)
        assert done == want_done > 0
        assert np.all(np.isfinite(step))
        np.testing.assert_allclose(t, want.t_m2c, atol=1e-6)
        assert rotation_angle_deg(R, want.R_m2c) < 1e-6
        pose = Pose(R, t)
    assert rotation_angle_deg(pose.R_m2c, truth.R_m2c) < 1.0


def test_search_priors_hold_each_half_length():
    table = _search_priors(8)
    for k in range(1, 9):
        np.testing.assert_array_equal(table[k, :2 * k - 1], _search_prior(k))
        assert not table[k, 2 * k - 1:].any()
