"""The image edge along each contour normal, compiled (the refinement's inner loop).

The pose refinement (:mod:`viewloc_core.refine`) looks for the image edge
along each projected contour normal several times per Gauss-Newton fit. In
array form each look is a ``cv2.remap`` of a (K offsets, N points) sample map
followed by a dozen passes over (K, N) temporaries; here each point is one
short loop.

Sampling reproduces ``cv2.remap(..., INTER_LINEAR, BORDER_CONSTANT, 0)`` of a
two-channel float32 image bit for bit (OpenCV 5.0): each coordinate is
rounded to 1/32 pixel (half to even), and the four neighbours (0 outside the
image) are summed left to right in float32 with weights that are exact
products of multiples of 1/32. The refinement's fits were tuned on those
samples, so they are kept exactly, and every later float32 step rounds as the
array form did. (One-channel images are sampled differently by OpenCV 5.0:
exact coordinates and fused multiply-adds; the shift search in
:func:`viewloc_core.refine._align_shift` keeps using ``cv2.remap`` for those,
whose vectorised code a scalar loop does not beat.)
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]

#: OpenCV's interpolation grid: coordinates are rounded to 1/32 pixel.
_TAB_SIZE = 32


@njit(cache=True, nogil=True)
def _pixel(
    flat: F32, w: int, h: int, x: np.int64, y: np.int64, channel: int,
) -> np.float32:  # pragma: no cover - compiled
    """One channel of pixel (x, y) of an (h, w, 2) image given flat; 0 outside
    the image, as ``cv2.remap``'s constant border."""
    if 0 <= x < w and 0 <= y < h:
        return flat[(y * w + x) * 2 + channel]
    return np.float32(0.0)


@njit(cache=True, nogil=True)
def search_normals(
    grad: F32, uv: F64, normal: F64, search: int, min_gradient: float, cos_max: float,
    prior: F64,
) -> tuple[NDArray[np.bool_], F64]:  # pragma: no cover - compiled
    """The nearest strong edge along each normal, to sub-pixel precision.

    Parameters
    ----------
    grad : (H, W, 2) float32
        Interleaved (∂I/∂x, ∂I/∂y) of one pyramid level, intensity per pixel.
    uv : (N, 2) float64
        Points on that level, pixels.
    normal : (N, 2) float64
        Unit normals.
    search : int
        The line runs ``-search .. search`` level pixels along the normal
        (K = 2 search + 1 samples).
    min_gradient : float
        Weakest gradient component along the normal taken as an edge.
    cos_max : float
        Cosine of the largest angle between the gradient and the normal.
    prior : (K - 2,) float64
        Weight of each interior offset (nearer edges preferred).

    Returns
    -------
    found : (N,) bool
        A local maximum of the edge response lies inside the line (not at
        either end, which is only the slope of an edge beyond it).
    offset_px : (N,) float64
        Its offset along the normal, level pixels, refined by a parabola
        through the three samples around it and clamped to ±0.5 px;
        meaningful only where ``found``.
    """
    n = uv.shape[0]
    h, w = grad.shape[0], grad.shape[1]
    flat = grad.reshape(-1)
    k_count = 2 * search + 1
    found = np.zeros(n, np.bool_)
    offset = np.empty(n, np.float64)
    along = np.empty(k_count, np.float32)
    score = np.empty(k_count, np.float32)
    floor = np.float32(min_gradient)
    cos_sq = np.float32(cos_max * cos_max)
    zero = np.float32(0.0)
    one = np.float32(1.0)
    for i in range(n):
        u = np.float32(uv[i, 0])
        v = np.float32(uv[i, 1])
        nx = np.float32(normal[i, 0])
        ny = np.float32(normal[i, 1])
        # Lines that stay a pixel inside the image read it without checks.
        reach_x = search * abs(normal[i, 0])
        reach_y = search * abs(normal[i, 1])
        inside = (uv[i, 0] - reach_x >= 1.0 and uv[i, 1] - reach_y >= 1.0
                  and uv[i, 0] + reach_x <= w - 3.0 and uv[i, 1] + reach_y <= h - 3.0)
        for k in range(k_count):
            step = np.float32(k - search)
            # cv2.remap's sampling of a two-channel float32 image: the point
            # rounded to 1/32 px, bilinear weights of multiples of 1/32.
            ix = np.int64(np.rint((step * nx + u) * np.float32(_TAB_SIZE)))
            iy = np.int64(np.rint((step * ny + v) * np.float32(_TAB_SIZE)))
            x0 = ix >> 5
            y0 = iy >> 5
            if inside:
                p = (y0 * w + x0) * 2
                q = p + 2 * w
                a0, b0, c0, d0 = flat[p], flat[p + 2], flat[q], flat[q + 2]
                a1, b1, c1, d1 = flat[p + 1], flat[p + 3], flat[q + 1], flat[q + 3]
            else:
                a0, a1 = _pixel(flat, w, h, x0, y0, 0), _pixel(flat, w, h, x0, y0, 1)
                b0, b1 = _pixel(flat, w, h, x0 + 1, y0, 0), _pixel(flat, w, h, x0 + 1, y0, 1)
                c0, c1 = _pixel(flat, w, h, x0, y0 + 1, 0), _pixel(flat, w, h, x0, y0 + 1, 1)
                d0 = _pixel(flat, w, h, x0 + 1, y0 + 1, 0)
                d1 = _pixel(flat, w, h, x0 + 1, y0 + 1, 1)
            fx = np.float32(ix & 31) / np.float32(_TAB_SIZE)
            fy = np.float32(iy & 31) / np.float32(_TAB_SIZE)
            w00 = (one - fy) * (one - fx)
            w01 = (one - fy) * fx
            w10 = fy * (one - fx)
            w11 = fy * fx
            g0 = a0 * w00 + b0 * w01 + c0 * w10 + d0 * w11
            g1 = a1 * w00 + b1 * w01 + c1 * w10 + d1 * w11
            a = abs(g0 * nx + g1 * ny)
            along[k] = a
            # |g·n| >= cos(max angle)·|g|, squared to skip the square root.
            limit = (g0 * g0 + g1 * g1) * cos_sq
            score[k] = a if (a >= floor and a * a >= limit) else zero
        best = 0
        best_weight = 0.0
        any_peak = False
        for k in range(1, k_count - 1):
            s = score[k]
            if s > zero and s >= max(score[k - 1], score[k + 1]):
                any_peak = True
                weight = np.float64(s) * prior[k - 1]
                if weight > best_weight:
                    best_weight = weight
                    best = k - 1
        found[i] = any_peak
        left = np.float64(along[best])
        centre = np.float64(along[best + 1])
        right = np.float64(along[best + 2])
        denom = left - 2.0 * centre + right
        sub = 0.0
        if abs(denom) > 1e-12:
            sub = 0.5 * (left - right) / denom
        sub = min(max(sub, -0.5), 0.5)
        offset[i] = best + (1 - search) + sub
    return found, offset


def warm_up() -> None:
    """Compile the kernel for the types the refinement passes."""
    grad = np.zeros((4, 4, 2), np.float32)
    uv = np.ones((1, 2))
    search_normals(grad, uv, uv, 1, 0.1, 0.5, np.ones(1))
