"""The shading agreement's two steps, compiled: which surface samples the
camera sees, and the robust spherical-harmonics fit of their intensities;
and the mask of the pixels projected points fall on.

:func:`viewloc_core.shading.shading_agreement` judges every rival start of
a fit (:func:`viewloc_core.localize`: 10-20 calls per image on a part with
near-symmetries) on 2000 surface samples. In array form each call was about
40 numpy calls on arrays too short to pay off, and a 9x9 least-squares
solve per reweighting pass (about 0.9 ms a call); here it is two calls
around OpenCV's bilinear read of the image. The arithmetic is the array
form's; only the order of some sums differs.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

from viewloc_core.contour_kernels import to_pixel
from viewloc_core.robust import TUKEY_C

F64 = NDArray[np.float64]

#: numpy's default cut-off of small singular values in ``lstsq`` for a 9x9
#: system (machine epsilon times the larger dimension): a flat face's
#: normals leave the normal equations rank-deficient.
_LSTSQ_RCOND = 9.0 * float(np.finfo(np.float64).eps)


@njit(cache=True, nogil=True)
def visible_samples(
    points_mm: F64, normals: F64, R_m2c: F64, t_m2c: F64, intrinsics: F64, dist: F64,
    distorted: bool, width: int, height: int, spacing_mm: float, min_facing_cos: float,
) -> tuple[F64, F64, NDArray[np.int64]]:  # pragma: no cover - compiled
    """Image positions and camera-frame normals of the samples the camera sees.

    Parameters
    ----------
    points_mm, normals : (N, 3) float64
        Surface samples and their unit normals, object frame.
    R_m2c : (3, 3) float64
    t_m2c : (3,) float64
        The pose, object -> camera, mm.
    intrinsics : (4,) float64
        ``fx, fy, cx, cy``.
    dist : (8,) float64
        Distortion coefficients, zero-padded (used when ``distorted``).
    distorted : bool
    width, height : int
        Image size, pixels.
    spacing_mm : float
        Typical distance between neighbouring samples.
    min_facing_cos : float
        Samples whose normal makes a smaller cosine with the ray to the
        camera are dropped.

    Returns
    -------
    uv : (M, 2) float64
        Pixel positions, inside the image.
    normals_cam : (M, 3) float64
        Their normals, camera frame.
    index : (M,) int64
        Their indices among the samples, increasing.
    """
    n = points_mm.shape[0]
    uv = np.empty((n, 2))
    normals_cam = np.empty((n, 3))
    index = np.empty(n, np.int64)
    z = np.empty(n)
    m = 0
    for i in range(n):
        px, py, pz = points_mm[i, 0], points_mm[i, 1], points_mm[i, 2]
        x = R_m2c[0, 0] * px + R_m2c[0, 1] * py + R_m2c[0, 2] * pz + t_m2c[0]
        y = R_m2c[1, 0] * px + R_m2c[1, 1] * py + R_m2c[1, 2] * pz + t_m2c[1]
        zc = R_m2c[2, 0] * px + R_m2c[2, 1] * py + R_m2c[2, 2] * pz + t_m2c[2]
        if zc <= 1e-6:
            continue
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        ncx = R_m2c[0, 0] * nx + R_m2c[0, 1] * ny + R_m2c[0, 2] * nz
        ncy = R_m2c[1, 0] * nx + R_m2c[1, 1] * ny + R_m2c[1, 2] * nz
        ncz = R_m2c[2, 0] * nx + R_m2c[2, 1] * ny + R_m2c[2, 2] * nz
        norm = max(math.sqrt(x * x + y * y + zc * zc), 1e-12)
        if -(ncx * x + ncy * y + ncz * zc) / norm <= min_facing_cos:
            continue
        u, v = to_pixel(x, y, zc, intrinsics, dist, distorted)
        if not (0.0 <= u <= width - 1 and 0.0 <= v <= height - 1):
            continue
        uv[m, 0] = u
        uv[m, 1] = v
        normals_cam[m, 0] = ncx
        normals_cam[m, 1] = ncy
        normals_cam[m, 2] = ncz
        index[m] = i
        z[m] = zc
        m += 1
    if m == 0:
        return uv[:0], normals_cam[:0], index[:0]
    # Facing the camera is not enough on a concave part: of the samples that
    # land in one cell of a coarse depth buffer, only those near the nearest
    # are seen. A cell is about three samples wide at the part's distance,
    # so that few cells of a nearer surface are left without a sample of it
    # (the samples are random, not a grid).
    cell_px = max(1.0, 3.0 * spacing_mm * intrinsics[0] / np.median(z[:m]))
    cells = np.empty(m)
    for i in range(m):
        cells[i] = (math.floor(uv[i, 1] / cell_px) * (width / cell_px + 1)
                    + math.floor(uv[i, 0] / cell_px))
    order = np.argsort(cells)
    nearest = np.empty(m)
    start = 0
    while start < m:
        stop = start
        lowest = np.inf
        while stop < m and cells[order[stop]] == cells[order[start]]:
            lowest = min(lowest, z[order[stop]])
            stop += 1
        for k in range(start, stop):
            nearest[order[k]] = lowest
        start = stop
    seen = np.flatnonzero(z[:m] <= nearest + 2.0 * spacing_mm)
    return uv[seen], normals_cam[seen], index[seen]


@njit(cache=True, nogil=True)
def _tukey(residual: F64, min_scale: float) -> F64:  # pragma: no cover - compiled
    """:func:`viewloc_core.robust.tukey_weights`'s weights, compiled (the
    kernel test checks the fit against the array form that calls it)."""
    mad = np.median(np.abs(residual - np.median(residual)))
    scale = max(1.4826 * mad, min_scale)
    u = residual / (TUKEY_C * scale)
    w = np.maximum(1.0 - u * u, 0.0)
    return w * w


@njit(cache=True, nogil=True)
def explained_variance(intensity: F64, normals_cam: F64, albedo: F64,
                       passes: int) -> float:  # pragma: no cover - compiled
    """Share of the intensities' variance a robust fit on their normals'
    first nine spherical harmonics explains, each scaled by the surface's
    own brightness there when it has a pattern.

    Parameters
    ----------
    intensity : (M,) float64
        Image brightness at the samples.
    normals_cam : (M, 3) float64
        Their unit normals.
    albedo : (M,) or (0,) float64
        The part's own brightness at the samples (0..1), or empty for a part
        of one colour. Given, the fit is ``albedo * SH(normal) . c + b``:
        the light scales the part's pattern, and ``b`` takes the camera's
        black level and ambient light, which do not.
    passes : int
        Reweighting passes (Tukey's biweight on the residuals).

    Returns
    -------
    float
        In [0, 1]; NaN when nothing is left to explain (every weight zero,
        or a uniform part).
    """
    m = len(intensity)
    patterned = len(albedo) == m
    columns = 10 if patterned else 9
    basis = np.empty((m, columns))
    for i in range(m):
        x, y, zz = normals_cam[i, 0], normals_cam[i, 1], normals_cam[i, 2]
        a = albedo[i] if patterned else 1.0
        basis[i, 0] = a
        basis[i, 1] = a * x
        basis[i, 2] = a * y
        basis[i, 3] = a * zz
        basis[i, 4] = a * x * y
        basis[i, 5] = a * x * zz
        basis[i, 6] = a * y * zz
        basis[i, 7] = a * (x * x - y * y)
        basis[i, 8] = a * (3.0 * zz * zz - 1.0)
        if patterned:
            basis[i, 9] = 1.0
    weights = np.ones(m)
    residual = intensity - intensity.mean()
    # The scale's floor is far below any image noise: it only keeps an exact
    # fit (a synthetic image) from dividing by zero.
    min_scale = 1e-9 * (1.0 + np.abs(intensity).max())
    for _ in range(passes):
        weighted = basis.T * weights
        coef = np.linalg.lstsq(weighted @ basis, weighted @ intensity, _LSTSQ_RCOND)[0]
        residual = intensity - basis @ coef
        weights = _tukey(residual, min_scale)
    total_weight = weights.sum()
    if total_weight <= 0.0:
        return np.nan
    mean = (weights @ intensity) / total_weight
    spread = weights @ ((intensity - mean) ** 2)
    if spread <= 1e-9 * total_weight * max(1.0, mean * mean):
        return np.nan
    return min(max(1.0 - (weights @ (residual ** 2)) / spread, 0.0), 1.0)


@njit(cache=True, nogil=True)
def points_mask(uv: F64, x0: int, y0: int, height: int,
                width: int) -> NDArray[np.uint8]:  # pragma: no cover - compiled
    """A (height, width) uint8 box at pixel ``(x0, y0)`` with 1 at the pixel
    each of the (N, 2) image points ``uv`` rounds to (half to even, as
    numpy rounds) that falls inside it, 0 elsewhere; points that are not
    finite fall nowhere.

    Every rival fit's ranking draws its silhouette and its contour this way
    (:mod:`viewloc_core.interior_edges`): in array form six numpy calls on
    2000 points, about 0.06 ms each time.
    """
    out = np.zeros((height, width), np.uint8)
    for i in range(uv.shape[0]):
        u = np.rint(uv[i, 0] - x0)
        v = np.rint(uv[i, 1] - y0)
        # False for NaN as well.
        if 0.0 <= u < width and 0.0 <= v < height:
            out[int(v), int(u)] = 1
    return out


def warm_up() -> None:
    """Compile (or load from numba's cache) for the types the shading passes."""
    rng = np.random.default_rng(0)
    normals = rng.normal(size=(60, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    visible_samples(rng.normal(size=(60, 3)), normals, np.eye(3), np.array([0.0, 0.0, 500.0]),
                    np.array([500.0, 500.0, 320.0, 240.0]), np.zeros(8), False, 640, 480, 1.0,
                    0.3)
    explained_variance(rng.random(60), normals, np.empty(0), 4)
    explained_variance(rng.random(60), normals, rng.random(60), 4)
    points_mask(rng.random((5, 2)), 0, 0, 2, 3)
