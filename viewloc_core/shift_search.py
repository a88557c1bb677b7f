"""How well a projected contour meets the image edges under every 2D shift, compiled.

The refinement starts with an exhaustive search over integer 2D shifts of the
whole projected contour (:func:`viewloc_core.refine._align_shift`): the
chamfer-like score of a shift is the sum over contour points of the image
gradient along the point's normal, read at the shifted point (bilinear) and
saturated. In array form that is two ``cv2.remap`` calls over an
(S shifts, N points) sample map, about a millisecond per fit, and it runs at
the start of every fit. Here the shifts are integers, so each point's
bilinear weights are the same for every shift; and the gradient along a fixed
normal is linear in the gradient, so it is formed once per pixel of the
point's neighbourhood and interpolated after. That is several times less work.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]


@njit(cache=True, nogil=True)
def shift_scores(
    grad: F32, uv: F64, normal: F64, rad: int, cap: float,
) -> F64:  # pragma: no cover - compiled
    """Score of every integer shift within ±``rad`` of a contour.

    Parameters
    ----------
    grad : (H, W, 2) float32
        Interleaved (∂I/∂x, ∂I/∂y) of one pyramid level, intensity per pixel.
    uv : (N, 2) float64
        Contour points on that level, pixels.
    normal : (N, 2) float64
        Their unit normals.
    rad : int
        Largest shift along each axis, level pixels.
    cap : float
        Each point's contribution is at most this (so that a few very strong
        clutter edges cannot outvote the outline).

    Returns
    -------
    (S,) float64
        ``sum_i min(|g(uv_i + s) · n_i|, cap)`` for the S = (2 rad + 1)²
        shifts s = (dx, dy), row-major with dx fastest (dy = -rad first), the
        zero shift in the middle; the gradient is bilinear between pixel
        centres and 0 outside the image.
    """
    h, w = grad.shape[0], grad.shape[1]
    side = 2 * rad + 1
    patch_side = side + 1
    scores = np.zeros(side * side, np.float64)
    along = np.empty((patch_side, patch_side), np.float32)
    cap32 = np.float32(cap)
    one = np.float32(1.0)
    for i in range(uv.shape[0]):
        fx0 = math.floor(uv[i, 0])
        fy0 = math.floor(uv[i, 1])
        fx = np.float32(uv[i, 0] - fx0)
        fy = np.float32(uv[i, 1] - fy0)
        x_first = np.int64(fx0) - rad
        y_first = np.int64(fy0) - rad
        nx = np.float32(normal[i, 0])
        ny = np.float32(normal[i, 1])
        # The gradient along the normal on every pixel any shift reads.
        for r in range(patch_side):
            y = y_first + r
            for c in range(patch_side):
                x = x_first + c
                if 0 <= x < w and 0 <= y < h:
                    along[r, c] = grad[y, x, 0] * nx + grad[y, x, 1] * ny
                else:
                    along[r, c] = np.float32(0.0)
        w00 = (one - fy) * (one - fx)
        w01 = (one - fy) * fx
        w10 = fy * (one - fx)
        w11 = fy * fx
        for r in range(side):
            top = along[r]
            bottom = along[r + 1]
            base = r * side
            for c in range(side):
                value = abs(top[c] * w00 + top[c + 1] * w01 + bottom[c] * w10
                            + bottom[c + 1] * w11)
                scores[base + c] += min(value, cap32)
    return scores


@functools.lru_cache(maxsize=16)
def shift_grid(rad: int) -> tuple[F32, F64]:
    """The shifts :func:`shift_scores` scores, in its order, and their squared lengths.

    Returns
    -------
    shifts : ((2 rad + 1)², 2) float32
        Integer shifts (dx, dy), row-major with dx fastest, the zero shift
        in the middle.
    dist2 : ((2 rad + 1)²,) float64
        Their squared lengths, pixels².
    """
    grid = np.arange(-rad, rad + 1, dtype=np.float32)
    sx, sy = np.meshgrid(grid, grid)
    shifts = np.column_stack([sx.ravel(), sy.ravel()])
    return shifts, (shifts.astype(np.float64) ** 2).sum(axis=1)


def warm_up() -> None:
    """Compile the kernel for the types the refinement passes."""
    shift_scores(np.zeros((4, 4, 2), np.float32), np.ones((1, 2)), np.ones((1, 2)), 1, 1.0)
