"""The similarity each (image feature, model feature) pairing implies, compiled.

A pairing of an image feature at ``(x, y, θ, s)`` with a model feature at
``(x', y', θ', s')`` in its model view's frame implies the similarity model
view -> image with angle ``θ - θ'``, scale ``s / s'`` and the translation that
maps ``(x', y')`` onto ``(x, y)``. A parallel pair's orientation is known only
modulo π, so a pairing with one implies a second similarity, turned by π.

A busy image pairs tens of thousands of times; in array form this was a dozen
passes over all of them (and the largest single cost of seeding the
alignment), here it is one.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@njit(cache=True, nogil=True)
def _seed_into(out: F64, src: I64, n_out: int, i: int, angle: float, scale: float,
               ix: float, iy: float, mx: float, my: float) -> int:  # pragma: no cover
    """Write pairing ``i``'s similarity at row ``n_out``; the next free row."""
    c = scale * math.cos(angle)
    s = scale * math.sin(angle)
    out[n_out, 0] = ix - (c * mx - s * my)
    out[n_out, 1] = iy - (s * mx + c * my)
    # Wrapped to (-π, π] as similarity.wrap_angle does.
    out[n_out, 2] = -(((-angle + math.pi) % (2.0 * math.pi)) - math.pi)
    out[n_out, 3] = scale
    src[n_out] = i
    return n_out + 1


@njit(cache=True, nogil=True)
def seed_similarities(
    img_xy: NDArray[np.float32], img_theta: NDArray[np.float32],
    img_scale: NDArray[np.float32], model_xy: F64, model_theta: F64, model_scale: F64,
    model_parallel: NDArray[np.bool_], k: I64, j: I64, min_scale: float, max_scale: float,
) -> tuple[F64, I64]:  # pragma: no cover - compiled
    """Similarities implied by pairings, those with a scale in range.

    Parameters
    ----------
    img_xy : (G, 2) float32
        Image feature positions, pixels.
    img_theta, img_scale : (G,) float32
        Their orientations (radians) and scales (pixels).
    model_xy : (F, 2) float64
        Model feature positions in their model view's frame, pixels.
    model_theta, model_scale : (F,) float64
    model_parallel : (F,) bool
        Which model features are parallel pairs.
    k, j : (N,) int64
        Image and model feature of each pairing.
    min_scale, max_scale : float
        Range of the implied scale kept (inclusive).

    Returns
    -------
    sims : (M, 4) float64
        ``(x, y, angle_rad, scale)`` model view -> image; the pairings in
        order, then the π-turned similarities of the parallel pairs in order.
    pairing : (M,) int64
        The pairing (index into ``k``, ``j``) each came from.
    """
    n = len(k)
    n_parallel = 0
    for i in range(n):
        if model_parallel[j[i]]:
            n_parallel += 1
    out = np.empty((n + n_parallel, 4))
    src = np.empty(n + n_parallel, np.int64)
    n_out = 0
    for turn in range(2):
        for i in range(n):
            ki, ji = k[i], j[i]
            if turn == 1 and not model_parallel[ji]:
                continue
            scale = np.float64(img_scale[ki]) / model_scale[ji]
            if not (scale >= min_scale and scale <= max_scale):
                continue
            angle = np.float64(img_theta[ki]) - model_theta[ji]
            if turn == 1:
                angle = angle + math.pi
            n_out = _seed_into(out, src, n_out, i, angle, scale, np.float64(img_xy[ki, 0]),
                               np.float64(img_xy[ki, 1]), model_xy[ji, 0], model_xy[ji, 1])
    return out[:n_out], src[:n_out]


def warm_up() -> None:
    """Compile (or load from numba's cache) for the types the alignment passes."""
    f32 = np.zeros(1, np.float32)
    seed_similarities(np.zeros((1, 2), np.float32), f32, f32 + 1, np.zeros((1, 2)),
                      np.zeros(1), np.ones(1), np.zeros(1, np.bool_), np.zeros(1, np.int64),
                      np.zeros(1, np.int64), 0.5, 2.0)
