"""The refinement's inner steps, compiled: project a view's contour, match it
to the image edges and linearise the residuals.

Each Gauss-Newton iteration of :func:`viewloc_core.refine.refine_pose`
projects a few hundred contour points and their normals and searches the
image along each normal. In array form that was two dozen numpy calls per
iteration on arrays too short for numpy to pay off (about 60 % of a
refinement's time, and a localization runs 10-40 refinements); here it is
two calls. The arithmetic is the array form's, point by point.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from viewloc_core.normal_search import search_normals

F64 = NDArray[np.float64]
#: Contour points come as float64 (stacked by the projector) or as the
#: model's own float32 (the compiled fit); the arithmetic is float64.
Points = NDArray[np.float32] | NDArray[np.float64]


@njit(cache=True, nogil=True)
def to_pixel(x: float, y: float, z: float, intrinsics: F64, dist: F64,
             distorted: bool) -> tuple[float, float]:  # pragma: no cover - compiled
    """Pixel of a camera-frame point (:meth:`viewloc_core.camera.Camera.project`),
    for the compiled kernels of the refinement and the shading."""
    u = x / z
    v = y / z
    if distorted:
        k1, k2, p1, p2, k3, k4, k5, k6 = (dist[0], dist[1], dist[2], dist[3], dist[4], dist[5],
                                          dist[6], dist[7])
        r2 = u * u + v * v
        radial = ((1 + r2 * (k1 + r2 * (k2 + r2 * k3)))
                  / (1 + r2 * (k4 + r2 * (k5 + r2 * k6))))
        ud = u * radial + 2 * p1 * u * v + p2 * (r2 + 2 * u * u)
        vd = v * radial + p1 * (r2 + 2 * v * v) + 2 * p2 * u * v
        u, v = ud, vd
    return u * intrinsics[0] + intrinsics[2], v * intrinsics[1] + intrinsics[3]


@njit(cache=True, nogil=True)
def project_contour(
    points: Points, normals: Points, R: F64, t: F64, intrinsics: F64, dist: F64,
    distorted: bool, window: F64,
) -> tuple[F64, F64, F64, NDArray[np.int64]]:  # pragma: no cover - compiled
    """Contour points seen at a pose: pixels, unit 2D normals, camera points
    and which of the input points they are.

    Parameters
    ----------
    points, normals : (N, 3) float32 or float64
        Contour points (mm) and their 3D normals, object frame.
    R : (3, 3) float64
        Rotation object -> camera.
    t : (3,) float64
        Translation, mm.
    intrinsics : (5,) float64
        ``fx, fy, cx, cy`` (pixels) and the focal length distances are
        measured in (``Camera.focal_px``).
    dist : (8,) float64
        OpenCV's distortion coefficients, zero-padded.
    distorted : bool
        Apply them.
    window : (4,) float64
        Centre (x, y) and half-size (x, y) of the image region kept, pixels.

    Returns
    -------
    uv : (M, 2) float64
        Pixels of the points in front of the camera (z > 1 mm) that project
        into the window with a defined normal.
    n2 : (M, 2) float64
        Unit image normals: towards where a step of about a pixel along
        the 3D normal projects.
    X : (M, 3) float64
        The points in the camera frame, mm.
    index : (M,) int64
        Row of each in ``points`` (ascending).
    """
    n = points.shape[0]
    uv = np.empty((n, 2))
    n2 = np.empty((n, 2))
    X = np.empty((n, 3))
    index = np.empty(n, np.int64)
    m = 0
    for i in range(n):
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        qx, qy, qz = normals[i, 0], normals[i, 1], normals[i, 2]
        x = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]
        y = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
        z = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2]
        if not z > 1.0:
            continue
        # A step of about a pixel along the 3D normal gives the 2D normal.
        step = z / intrinsics[4]
        sx = (R[0, 0] * qx + R[0, 1] * qy + R[0, 2] * qz) * step + x
        sy = (R[1, 0] * qx + R[1, 1] * qy + R[1, 2] * qz) * step + y
        sz = (R[2, 0] * qx + R[2, 1] * qy + R[2, 2] * qz) * step + z
        u, v = to_pixel(x, y, z, intrinsics, dist, distorted)
        su, sv = to_pixel(sx, sy, sz, intrinsics, dist, distorted)
        du = su - u
        dv = sv - v
        norm = math.sqrt(du * du + dv * dv)
        if not (abs(u - window[0]) <= window[2] and abs(v - window[1]) <= window[3]
                and norm > 1e-6):
            continue
        uv[m, 0] = u
        uv[m, 1] = v
        n2[m, 0] = du / norm
        n2[m, 1] = dv / norm
        X[m, 0] = x
        X[m, 1] = y
        X[m, 2] = z
        index[m] = i
        m += 1
    return uv[:m], n2[:m], X[:m], index[:m]


@njit(cache=True, nogil=True)
def nearest_view(directions: F64, R: F64, t: F64) -> int:  # pragma: no cover - compiled
    """Index of the view direction closest to where the camera sees from
    (the ``-Rᵀ t`` of :meth:`viewloc_core.contour_model.ContourModel.nearest_view`;
    the first of equals)."""
    d = np.empty(3)
    for k in range(3):
        d[k] = -(R[0, k] * t[0] + R[1, k] * t[1] + R[2, k] * t[2])
    if d[0] * d[0] + d[1] * d[1] + d[2] * d[2] < 1e-18:
        for k in range(3):
            d[k] = -R[2, k]
    best = 0
    best_dot = -np.inf
    for v in range(directions.shape[0]):
        dot = directions[v, 0] * d[0] + directions[v, 1] * d[1] + directions[v, 2] * d[2]
        if dot > best_dot:
            best_dot = dot
            best = v
    return best


@njit(cache=True, nogil=True)
def edge_residuals(
    grad: NDArray[np.float32], uv: F64, n2: F64, X: F64, t: F64, fx: float, fy: float,
    level: int, search: int, min_gradient: float, cos_max: float, prior: F64,
) -> tuple[F64, F64]:  # pragma: no cover - compiled
    """Residuals of the contour points that find an edge on one pyramid
    level, and their Jacobian (:func:`edge_residuals_of_points` without
    the points' indices)."""
    J, r, _ = edge_residuals_of_points(grad, uv, n2, X, t, fx, fy, level, search,
                                       min_gradient, cos_max, prior)
    return J, r


@njit(cache=True, nogil=True)
def edge_residuals_of_points(
    grad: NDArray[np.float32], uv: F64, n2: F64, X: F64, t: F64, fx: float, fy: float,
    level: int, search: int, min_gradient: float, cos_max: float, prior: F64,
) -> tuple[F64, F64, NDArray[np.int64]]:  # pragma: no cover - compiled
    """Residuals of the contour points that find an edge on one pyramid
    level, their Jacobian, and which points they are.

    Parameters
    ----------
    grad : (H_l, W_l, 2) float32
        Interleaved image gradient of the level.
    uv, n2, X : (N, 2), (N, 2), (N, 3) float64
        From :func:`project_contour` (full-resolution pixels).
    t : (3,) float64
        The pose's translation, mm: rotations turn about the object origin.
    fx, fy : float
        Focal lengths, pixels.
    level : int
        Pyramid level (0: full resolution).
    search, min_gradient, cos_max, prior
        As :func:`viewloc_core.normal_search.search_normals` takes them.

    Returns
    -------
    J : (M, 6) float64
        d residual / d (rotation vector, translation), full-resolution
        pixels per (rad, mm), rotation about the object origin.
    r : (M,) float64
        Residuals ``n · (π(X) - edge)``, full-resolution pixels.
    point : (M,) int64
        Index into ``uv`` of the point each residual belongs to.
    """
    f = 2.0**level
    n = uv.shape[0]
    uv_l = np.empty((n, 2))
    for i in range(n):
        if level:
            uv_l[i, 0] = (uv[i, 0] + 0.5) / f - 0.5
            uv_l[i, 1] = (uv[i, 1] + 0.5) / f - 0.5
        else:
            uv_l[i, 0] = uv[i, 0]
            uv_l[i, 1] = uv[i, 1]
    found, offset = search_normals(grad, uv_l, n2, search, min_gradient, cos_max, prior)
    m = 0
    for i in range(n):
        if found[i]:
            m += 1
    J = np.empty((m, 6))
    r = np.empty(m)
    point = np.empty(m, np.int64)
    k = 0
    for i in range(n):
        if not found[i]:
            continue
        point[k] = i
        # The matched edge lies offset·f pixels along n2 from the projection.
        r[k] = -offset[i] * f
        x, y, z = X[i, 0], X[i, 1], X[i, 2]
        # dπ/dX of the pinhole part (distortion is a small, smooth correction).
        a = n2[i, 0] * fx / z
        b = n2[i, 1] * fy / z
        c = -(a * x + b * y) / z
        # Rotation about the object origin: δX = ω × P + δt with P = X - t,
        # so n·J_π·(ω × P) = ω · (P × (J_πᵀ n)).
        px, py, pz = x - t[0], y - t[1], z - t[2]
        J[k, 0] = py * c - pz * b
        J[k, 1] = pz * a - px * c
        J[k, 2] = px * b - py * a
        J[k, 3] = a
        J[k, 4] = b
        J[k, 5] = c
        k += 1
    return J, r, point


def warm_up() -> None:
    """Compile (or load from numba's cache) for the types the refinement passes."""
    pts = np.array([[0.0, 0.0, 0.0]])
    nrm = np.array([[1.0, 0.0, 0.0]])
    uv, n2, X, _ = project_contour(pts, nrm, np.eye(3), np.array([0.0, 0.0, 100.0]),
                                np.array([100.0, 100.0, 8.0, 8.0, 100.0]), np.zeros(8), False,
                                np.array([8.0, 8.0, 7.0, 7.0]))
    edge_residuals(np.zeros((16, 16, 2), np.float32), uv, n2, X, np.zeros(3), 100.0, 100.0, 0,
                   3, 0.02, 0.8, np.ones(5))
    nearest_view(np.array([[0.0, 0.0, -1.0]]), np.eye(3), np.array([0.0, 0.0, 100.0]))
