"""One pyramid level of the refinement's Gauss-Newton fit, compiled.

:func:`viewloc_core.refine.refine_pose` runs up to 16 Gauss-Newton
iterations per fit and a localization runs 10-60 fits. Each iteration
projects the contour of the view nearest to the pose, matches it to the
image edges, weighs the residuals and solves a 6x6 system: two compiled
kernels (:mod:`viewloc_core.contour_kernels`) and about thirty small numpy
and OpenCV calls, whose overhead was two thirds of a fit's time and held
the GIL. Here a whole level is one call. The steps are the array form's:
the same projection and edge search, Tukey's biweight with the same scale,
Levenberg damping and a Cholesky solve, the update applied on the left.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from viewloc_core.contour_kernels import edge_residuals, nearest_view, project_contour
from viewloc_core.robust import TUKEY_C

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]

#: Robust standard deviation per median absolute deviation (Gaussian).
_MAD_TO_SIGMA = 1.4826

#: Relative and absolute Levenberg damping of the normal equations' diagonal.
_DAMPING_REL = 1e-3
_DAMPING_ABS = 1e-9


@njit(cache=True, nogil=True)
def tukey_weights(r: F64, min_scale: float) -> F64:  # pragma: no cover - compiled
    """Tukey biweights of residuals (:func:`viewloc_core.robust.tukey_weights`)."""
    med = np.median(r)
    mad = np.median(np.abs(r - med))
    scale = max(_MAD_TO_SIGMA * mad, min_scale)
    inv = 1.0 / (TUKEY_C * scale)
    w = np.empty_like(r)
    for i in range(len(r)):
        u = r[i] * inv
        wi = max(1.0 - u * u, 0.0)
        w[i] = wi * wi
    return w


@njit(cache=True, nogil=True)
def normal_equations(J: F64, r: F64, w: F64) -> tuple[F64, F64]:  # pragma: no cover - compiled
    """Weighted normal equations of a 6-parameter least-squares fit.

    Parameters
    ----------
    J : (M, 6) float64
        Jacobian of the residuals.
    r : (M,) float64
        Residuals.
    w : (M,) float64
        Their weights.

    Returns
    -------
    H : (6, 6) float64
        ``Jᵀ W J``, symmetric.
    g : (6,) float64
        ``Jᵀ W r``.
    """
    H = np.zeros((6, 6))
    g = np.zeros(6)
    for i in range(r.shape[0]):
        for a in range(6):
            wja = w[i] * J[i, a]
            g[a] += wja * r[i]
            for b in range(a, 6):
                H[a, b] += wja * J[i, b]
    for a in range(6):
        for b in range(a):
            H[a, b] = H[b, a]
    return H, g


@njit(cache=True, nogil=True)
def _solve_cholesky(H: F64, g: F64) -> tuple[bool, F64]:  # pragma: no cover - compiled
    """Solve H x = g for a symmetric positive definite 6x6 H; False when
    H is not positive definite."""
    n = 6
    L = np.zeros((n, n))
    for j in range(n):
        s = H[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:
            return False, np.zeros(n)
        L[j, j] = math.sqrt(s)
        for i in range(j + 1, n):
            s = H[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / L[j, j]
    y = np.empty(n)
    for i in range(n):
        s = g[i]
        for k in range(i):
            s -= L[i, k] * y[k]
        y[i] = s / L[i, i]
    x = np.empty(n)
    for i in range(n - 1, -1, -1):
        s = y[i]
        for k in range(i + 1, n):
            s -= L[k, i] * x[k]
        x[i] = s / L[i, i]
    return True, x


@njit(cache=True, nogil=True)
def rotation_from_vector(w0: float, w1: float, w2: float) -> F64:  # pragma: no cover
    """Rotation matrix of a rotation vector (rad), as ``cv2.Rodrigues``."""
    theta = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
    R = np.eye(3)
    if theta < 2.220446049250313e-16:
        return R
    c = math.cos(theta)
    s = math.sin(theta)
    c1 = 1.0 - c
    kx, ky, kz = w0 / theta, w1 / theta, w2 / theta
    R[0, 0] = c + c1 * kx * kx
    R[0, 1] = c1 * kx * ky - s * kz
    R[0, 2] = c1 * kx * kz + s * ky
    R[1, 0] = c1 * ky * kx + s * kz
    R[1, 1] = c + c1 * ky * ky
    R[1, 2] = c1 * ky * kz - s * kx
    R[2, 0] = c1 * kz * kx - s * ky
    R[2, 1] = c1 * kz * ky + s * kx
    R[2, 2] = c + c1 * kz * kz
    return R


@njit(cache=True, nogil=True)
def gauss_newton_level(
    grad: F32, points_obj: F32, normals_obj: F32, counts: NDArray[np.int32],
    directions: F64, stride: int, R0: F64, t0: F64, intrinsics: F64, dist: F64,
    distorted: bool, window: F64, level: int, search: int, iterations: int,
    min_gradient: float, cos_max: float, prior_by_search: F64, tol_px: float,
    tol_rot_deg: float, tol_trans_mm: float,
) -> tuple[F64, F64, int, F64]:  # pragma: no cover - compiled
    """Gauss-Newton iterations of the contour fit on one pyramid level.

    Parameters
    ----------
    grad : (H_l, W_l, 2) float32
        Interleaved image gradient of the level.
    points_obj, normals_obj : (V, P, 3) float32
        Contour points (mm) and 3D normals per view, object frame
        (:class:`viewloc_core.contour_model.ContourModel`).
    counts : (V,) int32
        Points of each view.
    directions : (V, 3) float64
        The views' unit directions, object frame.
    stride : int
        Every ``stride``-th point of a view is used.
    R0 : (3, 3) float64
        Starting rotation object -> camera.
    t0 : (3,) float64
        Starting translation, mm.
    intrinsics, dist, distorted, window
        As :func:`viewloc_core.contour_kernels.project_contour` takes them.
    level : int
        Pyramid level (0: full resolution).
    search : int
        Half-length of the search line, level pixels; on level 0 it shrinks
        to ``ceil(4 median |r| + 2)`` (at least 3) as the pose settles.
    iterations : int
        Most iterations.
    min_gradient, cos_max : float
        As :func:`viewloc_core.normal_search.search_normals` takes them.
    prior_by_search : (S + 1, 2 S - 1) float64
        Row ``k``: the search prior of a line of half-length ``k``
        (:func:`viewloc_core.refine._search_prior`), zero-padded; ``S`` at
        least ``search``.
    tol_px : float
        Convergence: every matched point moved less than this along its
        normal (full-resolution pixels).
    tol_rot_deg, tol_trans_mm : float
        Convergence also when the update is below both.

    Returns
    -------
    R : (3, 3) float64
    t : (3,) float64
        The pose reached.
    done : int
        Iterations run (an iteration stops early when fewer than 6 points
        find an edge or keep a weight, or the system cannot be solved).
    last_step : (3,) float64
        The last update's rotation (deg), translation (mm) and largest
        motion of a matched point along its normal (px); infinite when no
        update was made.
    """
    R = R0.copy()
    t = t0.copy()
    fx = intrinsics[0]
    fy = intrinsics[1]
    min_scale = 0.5 * 2.0**level
    last = np.full(3, np.inf)
    done = 0
    for _ in range(iterations):
        view = nearest_view(directions, R, t)
        n = counts[view]
        uv, n2, X, _ = project_contour(points_obj[view, :n:stride],
                                       normals_obj[view, :n:stride], R, t, intrinsics, dist,
                                       distorted, window)
        if uv.shape[0] == 0:
            break
        prior = prior_by_search[search, :2 * search - 1]
        J, r = edge_residuals(grad, uv, n2, X, t, fx, fy, level, search, min_gradient,
                              cos_max, prior)
        m = r.shape[0]
        if m < 6:
            break
        w = tukey_weights(r, min_scale)
        if np.count_nonzero(w) < 6:
            break
        H, g = normal_equations(J, r, w)
        for a in range(6):
            # Levenberg damping keeps a poorly constrained direction (e.g.
            # depth of a small part) from jumping.
            H[a, a] = H[a, a] * (1.0 + _DAMPING_REL) + _DAMPING_ABS
        ok, step = _solve_cholesky(H, g)
        if not ok:
            break
        finite = True
        for a in range(6):
            if not math.isfinite(step[a]):
                finite = False
        if not finite:
            break
        # The update is -step, applied on the left.
        dR = rotation_from_vector(-step[0], -step[1], -step[2])
        R = dR @ R
        for k in range(3):
            t[k] -= step[3 + k]
        done += 1
        motion = 0.0
        for i in range(m):
            move = 0.0
            for a in range(6):
                move += J[i, a] * step[a]
            motion = max(motion, abs(move))
        last[0] = math.degrees(math.sqrt(step[0] ** 2 + step[1] ** 2 + step[2] ** 2))
        last[1] = math.sqrt(step[3] ** 2 + step[4] ** 2 + step[5] ** 2)
        last[2] = motion
        if last[2] < tol_px * 2.0**level or (last[0] < tol_rot_deg and last[1] < tol_trans_mm):
            break
        # After the first levels the search can shrink as the pose settles.
        if level == 0:
            shrunk = int(math.ceil(4.0 * np.median(np.abs(r)) + 2.0))
            search = max(3, min(search, shrunk))
    return R, t, done, last


def warm_up() -> None:
    """Compile (or load from numba's cache) for the types the refinement passes."""
    pts = np.zeros((1, 1, 3), np.float32)
    nrm = np.zeros((1, 1, 3), np.float32)
    nrm[0, 0, 0] = 1.0
    gauss_newton_level(
        np.zeros((16, 16, 2), np.float32), pts, nrm, np.ones(1, np.int32),
        np.array([[0.0, 0.0, -1.0]]), 1, np.eye(3), np.array([0.0, 0.0, 100.0]),
        np.array([100.0, 100.0, 8.0, 8.0, 100.0]), np.zeros(8), False,
        np.array([8.0, 8.0, 7.0, 7.0]), 0, 3, 1, 0.02, 0.8, np.ones((4, 5)), 0.05, 0.01, 0.02)
