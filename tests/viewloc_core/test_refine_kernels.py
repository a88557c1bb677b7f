"""The refinement's compiled start and end against the array forms they replaced."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from tests.viewloc_core.test_refine import CAM, _clutter, _perturbed
from viewloc_core import robust
from viewloc_core.contour_kernels import edge_residuals_of_points
from viewloc_core.normal_search import search_normals
from viewloc_core.pose import Pose
from viewloc_core.refine import (
    RefineOptions,
    _Projector,
    _search_prior,
    prepare_edges,
)
from viewloc_core.refine_kernels import (
    chance_fraction,
    contour_neighbours,
    fit_measures,
    inflation_of,
    nearest_others,
    shifted_translation,
)
from viewloc_core.shift_search import shift_grid, shift_scores

SHIFTS = np.array([[9.0, 4.0], [-4.0, 9.0], [-9.0, -4.0], [4.0, -9.0]])


def _array_shift(pose, projector, edges, level, opts):
    """The start's shift search as refine._align_shift wrote it in array form."""
    proj = projector.project(pose, margin_px=1.0)
    if proj is None:
        return pose.t_m2c
    f = 2.0**level
    uv_l = (proj.uv + 0.5) / f - 0.5
    rad = max(1, int(math.ceil(opts.shift_search_px / f)))
    shifts, dist2 = shift_grid(rad)
    score = shift_scores(edges.gradients[level], uv_l, proj.n2, rad, 4.0 * opts.min_gradient)
    best = int(np.argmax(score - 1e-6 * dist2))
    if score[best] <= score[len(score) // 2] * 1.02:
        return pose.t_m2c
    shift_px = shifts[best].astype(np.float64) * f
    z = float(pose.t_m2c[2])
    cam = projector.camera
    return pose.t_m2c + np.array([shift_px[0] * z / cam.fx, shift_px[1] * z / cam.fy, 0.0])


def _array_chance(uv, n2, weight, grad, search, opts):
    """refine._chance_fraction's loop over the shifts, in array form."""
    cos_max = math.cos(math.radians(opts.max_angle_deg))
    rates = []
    for shift in SHIFTS:
        uv_s = uv + shift
        ok = ((uv_s[:, 0] >= 1) & (uv_s[:, 0] <= CAM.width - 2)
              & (uv_s[:, 1] >= 1) & (uv_s[:, 1] <= CAM.height - 2))
        if np.count_nonzero(ok) < 6:
            continue
        found, offset = search_normals(grad, np.ascontiguousarray(uv_s[ok]),
                                       np.ascontiguousarray(n2[ok]), search, opts.min_gradient,
                                       cos_max, _search_prior(search))
        total = float(weight[ok].sum())
        if total > 0:
            hit = found & (np.abs(offset) <= opts.inlier_px)
            rates.append(float(weight[ok][hit].sum()) / total)
    return float(np.mean(rates)) if rates else 1.0


@pytest.fixture(scope="module")
def cluttered_fits(bracket_contour_scene):
    """(edges, contour model, poses near and far from the truth) of a cluttered render."""
    renderer, prepared, model = bracket_contour_scene
    rng = np.random.default_rng(3)
    truth = Pose(Rotation.random(random_state=3).as_matrix(), np.array([30.0, -20.0, 600.0]))
    out = renderer.render(prepared, CAM, truth)
    edges = prepare_edges(np.where(out.mask[..., None], out.color, _clutter(rng)), 2)
    poses = [truth] + [_perturbed(truth, rng, a, d) for a, d in
                       [(2.0, 0.01), (5.0, -0.03), (12.0, 0.08), (30.0, 0.2)]]
    # Half out of the image, and behind the camera.
    poses.append(Pose(truth.R_m2c, truth.t_m2c + [330.0, 0.0, 0.0]))
    poses.append(Pose(truth.R_m2c, truth.t_m2c * [1.0, 1.0, -1.0]))
    return edges, model, poses


@pytest.mark.parametrize(("stride", "level", "reach_px"), [(1, 1, 16.0), (2, 1, 16.0),
                                                           (1, 0, 5.0)])
def test_shifted_translation_equals_the_array_form(cluttered_fits, stride, level, reach_px):
    edges, model, poses = cluttered_fits
    opts = RefineOptions(shift_search_px=reach_px, point_stride=stride)
    projector = _Projector(CAM, model, stride)
    moved = 0
    for pose in poses:
        got = shifted_translation(
            edges.gradients[level], model.points_obj, model.normals_obj, model.counts,
            model.directions, stride, pose.R_m2c, pose.t_m2c, projector.intrinsics,
            projector.dist, projector.distorted, projector.window(1.0), level,
            opts.shift_search_px, opts.min_gradient)
        want = _array_shift(pose, projector, edges, level, opts)
        np.testing.assert_array_equal(got, want)
        moved += not np.array_equal(got, pose.t_m2c)
    assert moved >= 2  # the test sees shifts made, not only starts kept


@pytest.mark.parametrize("stride", [1, 2])
def test_fit_measures_equal_the_array_form(cluttered_fits, stride):
    edges, model, poses = cluttered_fits
    opts = RefineOptions()
    projector = _Projector(CAM, model, stride, self_edge_weight=opts.self_edge_weight)
    search = 3
    cos_max = math.cos(math.radians(opts.max_angle_deg))
    for pose in poses:
        projected, n_inliers, values, H = fit_measures(
            edges.gradients[0], model.points_obj, model.normals_obj, model.kinds, model.counts,
            model.directions, stride, opts.self_edge_weight, pose.R_m2c, pose.t_m2c,
            projector.intrinsics, projector.dist, projector.distorted, projector.window(1.0),
            CAM.width, CAM.height, search, opts.min_gradient, cos_max, _search_prior(search),
            opts.inlier_px, SHIFTS, True, True)
        proj = projector.project(pose, margin_px=1.0)
        if proj is None:
            assert projected == 0
            continue
        assert projected == len(proj.uv)
        J, r, point = edge_residuals_of_points(
            edges.gradients[0], proj.uv, proj.n2, proj.X, pose.t_m2c, CAM.fx, CAM.fy, 0,
            search, opts.min_gradient, cos_max, _search_prior(search))
        inl = np.abs(r) <= opts.inlier_px
        assert n_inliers == np.count_nonzero(inl)
        # Weights of 1 and 1/2 sum exactly in any order.
        assert values[0] == proj.weight[point[inl]].sum()
        assert values[1] == proj.weight.sum()
        assert values[3] == _array_chance(proj.uv, proj.n2, proj.weight, edges.gradients[0],
                                          search, opts)
        if n_inliers < 6:
            continue
        assert values[2] == pytest.approx(np.abs(r[inl]).mean(), rel=1e-12)
        dist, _ = cKDTree(proj.uv).query(proj.uv, k=2)
        assert values[4] == pytest.approx(np.median(dist[:, 1]), rel=1e-12)
        w, _ = robust.tukey_weights(r[inl], 0.25)
        np.testing.assert_allclose(H, J[inl].T @ (J[inl] * w[:, None]), rtol=1e-9,
                                   atol=1e-12 * np.abs(H).max())
        assert values[6] == pytest.approx((w * r[inl] ** 2).sum() / max(w.sum() - 6.0, 1.0),
                                          rel=1e-12)
        assert values[5] >= 1.0


def test_fit_measures_skip_what_is_not_asked_for(cluttered_fits):
    edges, model, poses = cluttered_fits
    opts = RefineOptions()
    projector = _Projector(CAM, model)
    _, n_inliers, values, H = fit_measures(
        edges.gradients[0], model.points_obj, model.normals_obj, model.kinds, model.counts,
        model.directions, 1, 1.0, poses[0].R_m2c, poses[0].t_m2c, projector.intrinsics,
        projector.dist, projector.distorted, projector.window(1.0), CAM.width, CAM.height, 3,
        opts.min_gradient, 0.8, _search_prior(3), opts.inlier_px, SHIFTS, False, False)
    assert n_inliers > 50
    assert (values[3], values[4], values[5], values[6]) == (1.0, 0.0, 1.0, 0.0)
    assert not H.any()


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(2, 120))
def test_nearest_others_equal_a_tree_query(seed, n):
    rng = np.random.default_rng(seed)
    uv = rng.uniform(0.0, 200.0, (n, 2))
    nearest, distance = nearest_others(uv)
    dist, _ = cKDTree(uv).query(uv, k=2)
    np.testing.assert_allclose(distance, dist[:, 1], rtol=1e-12)
    # Whichever of equals it names, it is at that distance and not itself.
    assert np.all(nearest != np.arange(n))
    np.testing.assert_allclose(np.hypot(*(uv[nearest] - uv).T), dist[:, 1], rtol=1e-12)


def test_a_lone_point_has_no_neighbour():
    nearest, distance = nearest_others(np.array([[3.0, 4.0]]))
    assert nearest.tolist() == [-1] and np.isinf(distance).all()
    neighbour, spacing = contour_neighbours(np.array([[3.0, 4.0]]))
    assert neighbour.tolist() == [-1] and spacing == 0.0


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(6, 200))
def test_inflation_equals_the_correlation_formula(seed, n):
    rng = np.random.default_rng(seed)
    r = rng.normal(size=n) + 0.7 * np.sin(np.arange(n) / 3.0)
    r[rng.random(n) < 0.15] = np.nan
    neighbour = np.where(rng.random(n) < 0.1, -1, (np.arange(n) + 1) % n).astype(np.int64)
    ok = (neighbour >= 0) & np.isfinite(r)
    ok[ok] = np.isfinite(r[neighbour[ok]])
    a, b = r[ok], r[neighbour[ok]]
    if len(a) < 6:
        assert inflation_of(r, neighbour) == 1.0
        return
    rho = float(np.clip(np.corrcoef(a, b)[0, 1], 0.0, 0.95))
    assert inflation_of(r, neighbour) == pytest.approx((1.0 + rho) / (1.0 - rho), rel=1e-9)


def test_chance_fraction_ignores_shifts_that_leave_the_image():
    # Ten points on a strong vertical edge at x = 20; shifted by +-9 px
    # the contour meets nothing, and shifts pushing it out of a 24 px
    # wide image are not counted.
    grad = np.zeros((60, 24, 2), np.float32)
    grad[:, 20, 0] = 1.0
    uv = np.column_stack([np.full(10, 20.0), np.linspace(20.0, 40.0, 10)])
    n2 = np.tile([1.0, 0.0], (10, 1))
    weight = np.ones(10)
    rate = chance_fraction(grad, uv, n2, weight, np.array([[0.0, 0.0], [9.0, 0.0]]), 24, 60, 3,
                           0.1, 0.8, _search_prior(3), 2.0)
    assert rate == 1.0  # only the unshifted contour stayed inside, and it is all on the edge
    rate = chance_fraction(grad, uv, n2, weight, np.array([[0.0, 0.0], [-9.0, 0.0]]), 24, 60,
                           3, 0.1, 0.8, _search_prior(3), 2.0)
    assert rate == 0.5


def test_a_pose_viewed_from_a_matrix_needs_no_new_compilation(cluttered_fits):
    # Pose.from_matrix keeps views of the (4, 4) array, which are not
    # C-contiguous: passed as they are, every kernel would be compiled again
    # for them, for seconds, inside a request.
    from viewloc_core.gauss_newton_kernel import gauss_newton_level
    from viewloc_core.refine import refine_pose

    edges, model, poses = cluttered_fits
    refine_pose(edges, CAM, poses[1], model)
    kernels = (gauss_newton_level, shifted_translation, fit_measures)
    compiled = [len(k.signatures) for k in kernels]
    viewed = Pose.from_matrix(poses[1].matrix)
    assert not viewed.R_m2c.flags.c_contiguous
    assert refine_pose(edges, CAM, viewed, model).inlier_fraction > 0.5
    assert [len(k.signatures) for k in kernels] == compiled
