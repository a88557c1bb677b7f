"""The refinement's first and last steps, compiled: the 2D shift that starts
a fit, and the measures of the pose it ends at.

:func:`viewloc_core.refine.refine_pose` runs its Gauss-Newton levels as one
compiled call each (:mod:`viewloc_core.gauss_newton_kernel`). Around them it
searched the best 2D shift of the start and, at the end, counted the inliers,
measured the chance rate of the contour at nearby wrong places, the spacing
and neighbours of its points and the robust normal equations of the
covariance: some forty numpy, SciPy and OpenCV calls on arrays of a few
hundred points. Their overhead held the GIL for about half of a short fit's
time and three quarters of a full fit's measures, so two fits on two cores
(:func:`viewloc_core.both_cores.each_on_both`) mostly took turns. Here each
end is one call; the arithmetic is the array form's, so the poses, inlier
counts and chance rates are the same.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from viewloc_core.contour_kernels import edge_residuals_of_points, nearest_view, project_contour
from viewloc_core.contour_model import KIND_OCCLUDING
from viewloc_core.gauss_newton_kernel import normal_equations, tukey_weights
from viewloc_core.normal_search import search_normals
from viewloc_core.shift_search import shift_scores

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]

#: Neighbours whose residuals are compared lie within this many times the
#: median distance between neighbouring points (farther ones are across a
#: gap of the contour, or on another part of it).
NEIGHBOUR_SPACINGS = 2.0

#: The lag-one correlation is capped here (variance inflated at most 39-fold):
#: above it, the few points of a short contour say too little to tell.
MAX_RESIDUAL_CORRELATION = 0.95

#: Fewest inliers for a residual scale, a covariance or a correlation.
MIN_INLIERS = 6


@njit(cache=True, nogil=True)
def shifted_translation(
    grad: F32, points_obj: F32, normals_obj: F32, counts: NDArray[np.int32], directions: F64,
    stride: int, R: F64, t: F64, intrinsics: F64, dist: F64, distorted: bool, window: F64,
    level: int, shift_search_px: float, min_gradient: float,
) -> F64:  # pragma: no cover - compiled
    """The translation after the best 2D shift of the whole projected contour.

    The contour of the view nearest to ``(R, t)`` is projected and every
    integer shift of it within ``±shift_search_px`` (full-resolution pixels,
    on pyramid level ``level``) is scored (:func:`shift_scores`, each point
    capped at 4 ``min_gradient``); the best one, the smaller among near ties,
    moves the pose sideways at its depth unless it scores at most 2 % above
    no shift.

    Parameters
    ----------
    grad : (H_l, W_l, 2) float32
        Interleaved image gradient of the level.
    points_obj, normals_obj, counts, directions, stride
        The contour model as :func:`viewloc_core.gauss_newton_kernel.gauss_newton_level`
        takes it.
    R : (3, 3) float64
    t : (3,) float64
        The start, object -> camera, mm.
    intrinsics, dist, distorted, window
        As :func:`viewloc_core.contour_kernels.project_contour` takes them.
    level : int
        Pyramid level searched.
    shift_search_px : float
        Half-width of the search, full-resolution pixels (positive).
    min_gradient : float
        Weakest edge, intensity per pixel.

    Returns
    -------
    (3,) float64
        The shifted translation (a copy of ``t`` when no shift wins or
        nothing projects).
    """
    out = t.copy()
    view = nearest_view(directions, R, t)
    n = counts[view]
    uv, n2, _, _ = project_contour(points_obj[view, :n:stride], normals_obj[view, :n:stride],
                                   R, t, intrinsics, dist, distorted, window)
    if uv.shape[0] == 0:
        return out
    f = 2.0**level
    uv_l = np.empty_like(uv)
    for i in range(uv.shape[0]):
        uv_l[i, 0] = (uv[i, 0] + 0.5) / f - 0.5
        uv_l[i, 1] = (uv[i, 1] + 0.5) / f - 0.5
    rad = max(1, int(math.ceil(shift_search_px / f)))
    score = shift_scores(grad, uv_l, n2, rad, 4.0 * min_gradient)
    side = 2 * rad + 1
    best = 0
    best_key = -np.inf
    for s in range(side * side):
        dx = float(s % side - rad)
        dy = float(s // side - rad)
        # Prefer the smaller shift among (near) ties.
        key = score[s] - 1e-6 * (dx * dx + dy * dy)
        if key > best_key:
            best_key = key
            best = s
    if score[best] <= score[side * side // 2] * 1.02:
        return out
    z = t[2]
    out[0] = t[0] + float(best % side - rad) * f * z / intrinsics[0]
    out[1] = t[1] + float(best // side - rad) * f * z / intrinsics[1]
    return out


@njit(cache=True, nogil=True)
def nearest_others(uv: F64) -> tuple[NDArray[np.int64], F64]:  # pragma: no cover - compiled
    """Each point's nearest other point and the distance to it.

    Parameters
    ----------
    uv : (N, 2) float64
        Image positions, pixels.

    Returns
    -------
    nearest : (N,) int64
        Index of the nearest other point (the first of equals); -1 when
        there is none.
    distance : (N,) float64
        Its distance, pixels; infinite when there is none.
    """
    n = uv.shape[0]
    nearest = np.full(n, -1, np.int64)
    distance = np.full(n, np.inf)
    best2 = np.full(n, np.inf)
    # Each pair once: a contour has a few hundred points, and a grid or a
    # tree costs more to build than this loop takes.
    for i in range(n):
        xi = uv[i, 0]
        yi = uv[i, 1]
        for j in range(i + 1, n):
            dx = uv[j, 0] - xi
            dy = uv[j, 1] - yi
            d2 = dx * dx + dy * dy
            if d2 < best2[i]:
                best2[i] = d2
                nearest[i] = j
            if d2 < best2[j]:
                best2[j] = d2
                nearest[j] = i
    for i in range(n):
        distance[i] = math.sqrt(best2[i])
    return nearest, distance


@njit(cache=True, nogil=True)
def contour_neighbours(uv: F64) -> tuple[NDArray[np.int64], float]:  # pragma: no cover
    """Each point's nearest other point unless across a gap, and the spacing
    (:func:`viewloc_core.refine.nearest_neighbours`)."""
    n = uv.shape[0]
    if n < 2:
        return np.full(n, -1, np.int64), 0.0
    nearest, distance = nearest_others(uv)
    spacing = float(np.median(distance))
    for i in range(n):
        if not distance[i] <= NEIGHBOUR_SPACINGS * spacing:
            nearest[i] = -1
    return nearest, spacing


@njit(cache=True, nogil=True)
def inflation_of(residual_of_point: F64, neighbour: NDArray[np.int64]) -> float:  # pragma: no cover
    """Variance inflation of correlated neighbouring residuals
    (:func:`viewloc_core.refine.correlation_inflation`)."""
    n = residual_of_point.shape[0]
    a = np.empty(n)
    b = np.empty(n)
    m = 0
    for i in range(n):
        j = neighbour[i]
        if j >= 0 and math.isfinite(residual_of_point[i]) and math.isfinite(residual_of_point[j]):
            a[m] = residual_of_point[i]
            b[m] = residual_of_point[j]
            m += 1
    if m < MIN_INLIERS:
        return 1.0
    a = a[:m]
    b = b[:m]
    da = a - a.mean()
    db = b - b.mean()
    saa = float((da * da).sum())
    sbb = float((db * db).sum())
    if not (saa > 0.0 and sbb > 0.0):
        return 1.0
    rho = float((da * db).sum()) / math.sqrt(saa * sbb)
    rho = min(max(rho, 0.0), MAX_RESIDUAL_CORRELATION)
    return (1.0 + rho) / (1.0 - rho)


@njit(cache=True, nogil=True)
def chance_fraction(
    grad: F32, uv: F64, n2: F64, weight: F64, shifts: F64, width: int, height: int,
    search: int, min_gradient: float, cos_max: float, prior: F64, inlier_px: float,
) -> float:  # pragma: no cover - compiled
    """Weighted inlier fraction of a contour moved to nearby wrong places.

    Parameters
    ----------
    grad : (H, W, 2) float32
        Interleaved image gradient, full resolution.
    uv, n2 : (N, 2) float64
        The contour's pixels and unit normals at the pose.
    weight : (N,) float64
        Each point's weight in the fraction.
    shifts : (S, 2) float64
        The sideways shifts, pixels.
    width, height : int
        Image size: a shifted point must stay a pixel inside.
    search, min_gradient, cos_max, prior
        As :func:`search_normals` takes them.
    inlier_px : float
        An edge within this of a shifted point confirms it.

    Returns
    -------
    float
        Mean over the shifts that leave at least six points in the image
        (and some weight) of the weighted share of confirmed points; 1 when
        none does or there are fewer than two points.
    """
    n = uv.shape[0]
    if n < 2:
        return 1.0
    total_rate = 0.0
    n_rates = 0
    for s in range(shifts.shape[0]):
        uv_s = np.empty((n, 2))
        n2_s = np.empty((n, 2))
        w_s = np.empty(n)
        m = 0
        for i in range(n):
            x = uv[i, 0] + shifts[s, 0]
            y = uv[i, 1] + shifts[s, 1]
            if 1.0 <= x <= width - 2 and 1.0 <= y <= height - 2:
                uv_s[m, 0] = x
                uv_s[m, 1] = y
                n2_s[m, 0] = n2[i, 0]
                n2_s[m, 1] = n2[i, 1]
                w_s[m] = weight[i]
                m += 1
        if m < MIN_INLIERS:
            continue
        found, offset = search_normals(grad, uv_s[:m], n2_s[:m], search, min_gradient,
                                       cos_max, prior)
        total = 0.0
        hit = 0.0
        for i in range(m):
            total += w_s[i]
            if found[i] and abs(offset[i]) <= inlier_px:
                hit += w_s[i]
        if total > 0.0:
            total_rate += hit / total
            n_rates += 1
    return total_rate / n_rates if n_rates else 1.0


@njit(cache=True, nogil=True)
def fit_measures(
    grad: F32, points_obj: F32, normals_obj: F32, kinds: NDArray[np.uint8],
    counts: NDArray[np.int32], directions: F64, stride: int, self_edge_weight: float,
    R: F64, t: F64, intrinsics: F64, dist: F64, distorted: bool, window: F64,
    width: int, height: int, search: int, min_gradient: float, cos_max: float, prior: F64,
    inlier_px: float, chance_shifts: F64, measure_chance: bool, measure_uncertainty: bool,
) -> tuple[int, int, F64, F64]:  # pragma: no cover - compiled
    """Inliers, chance rate, spacing and robust normal equations of a final pose.

    Parameters
    ----------
    grad : (H, W, 2) float32
        Interleaved image gradient, full resolution.
    points_obj, normals_obj, counts, directions, stride
        As :func:`viewloc_core.gauss_newton_kernel.gauss_newton_level` takes them.
    kinds : (V, P) uint8
        Kind of each contour point (``KIND_*`` of :mod:`viewloc_core.contour_model`).
    self_edge_weight : float
        Weight of a point that is not on the outline.
    R : (3, 3) float64
    t : (3,) float64
        The pose, object -> camera, mm.
    intrinsics, dist, distorted, window
        As :func:`viewloc_core.contour_kernels.project_contour` takes them.
    width, height : int
        Image size.
    search, min_gradient, cos_max, prior
        The edge search at the pose (:func:`search_normals`).
    inlier_px : float
        A point is an inlier when its residual is at most this, pixels.
    chance_shifts : (S, 2) float64
        Shifts of :func:`chance_fraction`.
    measure_chance, measure_uncertainty : bool
        Measure the chance rate, spacing and correlation inflation; the
        normal equations.

    Returns
    -------
    projected : int
        Contour points projected into the window (0: nothing else is set).
    inliers : int
        Points with an edge within ``inlier_px``.
    values : (7,) float64
        Weighted inliers, weighted projected points, mean absolute inlier
        residual (px; infinite without inliers), chance fraction (1 when not
        measured), point spacing (px, 0 when not measured), correlation
        inflation (1 when not measured or under six inliers), the weighted
        residual variance ``sum(w r²) / max(sum(w) - 6, 1)`` of the Tukey
        weights (0 when not measured).
    normal_matrix : (6, 6) float64
        ``Jᵀ W J`` of the inliers (zeros when not measured or under six inliers).
    """
    values = np.zeros(7)
    values[2] = np.inf
    values[3] = 1.0
    values[5] = 1.0
    H = np.zeros((6, 6))
    view = nearest_view(directions, R, t)
    n = counts[view]
    uv, n2, X, index = project_contour(points_obj[view, :n:stride], normals_obj[view, :n:stride],
                                       R, t, intrinsics, dist, distorted, window)
    projected = uv.shape[0]
    if projected == 0:
        return 0, 0, values, H
    view_kinds = kinds[view, :n:stride]
    weight = np.empty(projected)
    for i in range(projected):
        # The outline weighs 1, the part's own edges ``self_edge_weight``.
        weight[i] = 1.0 if view_kinds[index[i]] == KIND_OCCLUDING else self_edge_weight
    J, r, point = edge_residuals_of_points(grad, uv, n2, X, t, intrinsics[0], intrinsics[1],
                                           0, search, min_gradient, cos_max, prior)
    inl = np.abs(r) <= inlier_px
    n_inliers = int(np.count_nonzero(inl))
    inliers_weighted = 0.0
    abs_sum = 0.0
    for k in range(r.shape[0]):
        if inl[k]:
            inliers_weighted += weight[point[k]]
            abs_sum += abs(r[k])
    values[0] = inliers_weighted
    values[1] = weight.sum()
    if n_inliers:
        values[2] = abs_sum / n_inliers
    if measure_chance:
        neighbour, spacing = contour_neighbours(uv)
        values[3] = chance_fraction(grad, uv, n2, weight, chance_shifts, width, height, search,
                                    min_gradient, cos_max, prior, inlier_px)
        values[4] = spacing
        if n_inliers >= MIN_INLIERS:
            # The outliers' residuals are left out.
            residual_of_point = np.full(projected, np.nan)
            for k in range(r.shape[0]):
                if inl[k]:
                    residual_of_point[point[k]] = r[k]
            values[5] = inflation_of(residual_of_point, neighbour)
    if measure_uncertainty and n_inliers >= MIN_INLIERS:
        r_in = r[inl]
        J_in = J[inl]
        w = tukey_weights(r_in, 0.25)
        H = normal_equations(J_in, r_in, w)[0]
        values[6] = float((w * r_in * r_in).sum()) / max(float(w.sum()) - 6.0, 1.0)
    return projected, n_inliers, values, H


def warm_up() -> None:
    """Compile (or load from numba's cache) for the types the refinement passes."""
    grad = np.zeros((16, 16, 2), np.float32)
    pts = np.zeros((1, 1, 3), np.float32)
    nrm = np.zeros((1, 1, 3), np.float32)
    nrm[0, 0, 0] = 1.0
    counts = np.ones(1, np.int32)
    directions = np.array([[0.0, 0.0, -1.0]])
    intrinsics = np.array([100.0, 100.0, 8.0, 8.0, 100.0])
    window = np.array([8.0, 8.0, 7.0, 7.0])
    shifted_translation(grad, pts, nrm, counts, directions, 1, np.eye(3),
                        np.array([0.0, 0.0, 100.0]), intrinsics, np.zeros(8), False, window,
                        1, 4.0, 0.02)
    fit_measures(grad, pts, nrm, np.zeros((1, 1), np.uint8), counts, directions, 1, 0.5,
                 np.eye(3), np.array([0.0, 0.0, 100.0]), intrinsics, np.zeros(8), False, window,
                 16, 16, 3, 0.02, 0.8, np.ones(3), 2.0, np.ones((1, 2)), True, True)
    contour_neighbours(np.zeros((3, 2)))
    inflation_of(np.zeros(3), np.zeros(3, np.int64))
