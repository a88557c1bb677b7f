"""The compiled similarity fit against the array formulation it replaced."""

from __future__ import annotations

import cv2
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from viewloc_core import similarity as sim2
from viewloc_core.features import ImageFeatures, extract_features
from viewloc_core.similarity_fit import _solve4, fit_similarities


def _array_fit(feats: ImageFeatures, sims, pts, theta, valid, radii, tol_deg, robust):
    """The batched numpy formulation (one array operation per step for all
    hypotheses), as align.extend_many computed it before it was compiled."""
    current = sims.copy()
    tol = np.radians(tol_deg)
    hh, pp = theta.shape
    alive = np.ones(hh, bool)
    for radius in radii:
        uv = sim2.apply_many(current, pts)
        found, nn = feats.nearest_edges(uv.reshape(-1, 2), radius)
        found = found.reshape(hh, pp) & valid
        nn = nn.reshape(hh, pp)
        img_theta = feats.edge_theta[nn].astype(np.float64)
        dth = np.abs(np.mod(theta + current[:, 2:3] - img_theta, np.pi))
        dth = np.minimum(dth, np.pi - dth)
        use = found & (dth < tol)
        wgt = use.astype(np.float64)
        nx, ny = -np.sin(img_theta), np.cos(img_theta)
        dst = feats.edge_xy[nn].astype(np.float64)
        if robust:
            resid = np.abs((uv[..., 0] - dst[..., 0]) * nx + (uv[..., 1] - dst[..., 1]) * ny)
            wgt *= np.where(resid <= 1.0, 1.0, 1.0 / np.maximum(resid, 1e-9))
        sx, sy = pts[..., 0], pts[..., 1]
        A = np.stack([nx * sx + ny * sy, -nx * sy + ny * sx, nx, ny], axis=-1)
        rhs = nx * dst[..., 0] + ny * dst[..., 1]
        Aw = A * wgt[..., None]
        AtA = np.matmul(Aw.transpose(0, 2, 1), A)
        Atb = np.matmul(Aw.transpose(0, 2, 1), rhs[..., None])[..., 0]
        ok = use.sum(axis=1) >= 6
        AtA[~ok] = np.eye(4)
        det = np.abs(np.linalg.det(AtA))
        if robust:
            trace = np.maximum(np.trace(AtA, axis1=1, axis2=2), 1e-12)
            ok &= det >= 1e-9 * trace**4
        else:
            ok &= det > 1e-9
        AtA[~ok] = np.eye(4)
        sol = np.linalg.solve(AtA, Atb[..., None])[..., 0]
        scale = np.hypot(sol[:, 0], sol[:, 1])
        ok &= (scale > 0.5 * current[:, 3]) & (scale < 2.0 * current[:, 3])
        new = np.stack([sol[:, 2], sol[:, 3], np.arctan2(sol[:, 1], sol[:, 0]), scale], axis=1)
        if robust:
            ok &= np.isfinite(new).all(axis=1) & alive
            alive = ok
        current[ok] = new[ok]
    return current


def _scene_and_samples():
    """An image of a few filled shapes and the edge samples of one of them
    in a model frame centred on it."""
    image = np.full((240, 320), 60, np.uint8)
    polygon = np.array([[100, 70], [190, 80], [205, 150], [150, 185], [95, 140]], np.int32)
    cv2.fillPoly(image, [polygon], 200)
    cv2.circle(image, (260, 60), 25, 140, -1)
    cv2.rectangle(image, (230, 150), (300, 220), 110, -1)
    feats = extract_features(image)
    near = np.hypot(*(feats.edge_xy - [150.0, 128.0]).T) < 80
    pts = feats.edge_xy[near].astype(np.float64) - [150.0, 128.0]
    theta = feats.edge_theta[near].astype(np.float64)
    return feats, pts, theta


def test_compiled_fit_equals_the_array_formulation():
    feats, pts, theta = _scene_and_samples()
    rng = np.random.default_rng(3)
    n_hyp = 40
    starts = np.column_stack([150.0 + rng.normal(0, 4, n_hyp), 128.0 + rng.normal(0, 4, n_hyp),
                              rng.normal(0, 0.08, n_hyp), np.exp(rng.normal(0, 0.05, n_hyp))])
    # Far-off starts too, where few or no samples pair (the degenerate paths).
    starts[-5:, :2] += [[120.0, 0.0], [0.0, 110.0], [-140.0, -100.0], [400.0, 0.0], [90.0, 60.0]]
    n_pts = len(pts)
    # Random subsets of the outline, as the padded sample sets of model views.
    valid = rng.random((n_hyp, n_pts)) < rng.uniform(0.4, 1.0, n_hyp)[:, None]
    pts_h = np.broadcast_to(pts, (n_hyp, n_pts, 2)).copy()
    theta_h = np.broadcast_to(theta, (n_hyp, n_pts)).copy()
    for robust, radii in ((False, (8.0, 4.0)), (True, (4.0, 2.5, 1.5, 1.5))):
        want = _array_fit(feats, starts, pts_h, theta_h, valid, radii, 20.0, robust)
        got = fit_similarities(starts, pts_h, theta_h, valid, feats.nearest_edge,
                               feats.edge_distance, feats.edge_xy, feats.edge_theta,
                               np.array(radii), np.radians(20.0), robust)
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9)
        moved = np.any(got != starts, axis=1)
        # Both the fitting and the kept-start paths are exercised.
        assert moved[:35].sum() >= (30 if not robust else 10)
        assert not moved[-2:].any()


@settings(max_examples=60, deadline=None)
@given(arrays(np.float64, (4, 4), elements=st.floats(-10, 10)),
       arrays(np.float64, 4, elements=st.floats(-10, 10)))
def test_four_by_four_solve_and_determinant_match_lapack(M, b):
    det, x = _solve4(M, b)
    want_det = np.linalg.det(M)
    assert abs(det - want_det) <= 1e-9 * max(1.0, np.abs(M).max() ** 4)
    if abs(want_det) > 1e-6 and np.linalg.cond(M) < 1e8:
        np.testing.assert_allclose(M @ x, b, atol=1e-6 * max(1.0, np.abs(b).max()))
