"""2D similarity transforms as 4-vectors ``(x, y, angle_rad, scale)``.

Arrays of similarities are handled in bulk (thousands of alignment seeds at
once), so this module works on ``(N, 4)`` float64 arrays; ``Similarity2D`` in
``detection.py`` is the single-value form for results. A similarity maps a
model-view point ``p`` to ``[x, y] + scale * Rot(angle) @ p`` (OpenCV pixels).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from viewloc_core.detection import Similarity2D

Array = NDArray[np.float64]


def apply(sim: NDArray[np.floating], pts: NDArray[np.floating]) -> Array:
    """Map points by one similarity.

    Parameters
    ----------
    sim : (4,) array
        ``(x, y, angle_rad, scale)``.
    pts : (N, 2) array
        Model-view points, pixels.

    Returns
    -------
    (N, 2) float64
    """
    x, y, a, s = (float(v) for v in sim)
    c, si = s * np.cos(a), s * np.sin(a)
    p = np.asarray(pts, dtype=np.float64)
    return np.stack([c * p[:, 0] - si * p[:, 1] + x, si * p[:, 0] + c * p[:, 1] + y], axis=1)


def apply_many(sims: NDArray[np.floating], pts: NDArray[np.floating]) -> Array:
    """Map points by many similarities.

    Parameters
    ----------
    sims : (H, 4) array
    pts : (P, 2) or (H, P, 2) array
        One point set for all similarities, or one per similarity.

    Returns
    -------
    (H, P, 2) float64
    """
    sims = np.asarray(sims, dtype=np.float64)
    c = (sims[:, 3] * np.cos(sims[:, 2]))[:, None]
    s = (sims[:, 3] * np.sin(sims[:, 2]))[:, None]
    px, py = pts[..., 0], pts[..., 1]
    return np.stack(
        [c * px - s * py + sims[:, 0:1], s * px + c * py + sims[:, 1:2]], axis=-1
    )


def compose(outer: NDArray[np.floating], inner: NDArray[np.floating]) -> Array:
    """``outer ∘ inner``: apply ``inner`` first. Both (4,) arrays."""
    return compose_many(outer, np.asarray(inner, dtype=np.float64)[None])[0]


def compose_many(outer: NDArray[np.floating], inner: NDArray[np.floating]) -> Array:
    """``outer ∘ inner[k]`` for each row of ``inner`` (H, 4); ``outer`` (4,). Returns (H, 4)."""
    x, y, a, sc = (float(v) for v in outer)
    inner = np.asarray(inner, dtype=np.float64)
    c, si = sc * np.cos(a), sc * np.sin(a)
    return np.stack([c * inner[:, 0] - si * inner[:, 1] + x,
                     si * inner[:, 0] + c * inner[:, 1] + y,
                     wrap_angle(a + inner[:, 2]), sc * inner[:, 3]], axis=1)


def inverse(sim: NDArray[np.floating]) -> Array:
    """Inverse similarity of a (4,) array."""
    x, y, a, s = (float(v) for v in sim)
    inv_s = 1.0 / s
    c, si = inv_s * np.cos(-a), inv_s * np.sin(-a)
    return np.array([-(c * x - si * y), -(si * x + c * y), -a, inv_s])


def wrap_angle(a: NDArray[np.floating] | float) -> Array:
    """Angles wrapped to (-π, π]."""
    return np.asarray(-(np.mod(-np.asarray(a, dtype=np.float64) + np.pi, 2 * np.pi) - np.pi))


def fit_points(
    src: NDArray[np.floating],
    dst: NDArray[np.floating],
    weights: NDArray[np.floating] | None = None,
) -> Array | None:
    """Weighted least-squares similarity mapping ``src`` onto ``dst`` (Umeyama 2D).

    Parameters
    ----------
    src, dst : (N, 2) arrays, N >= 2
    weights : (N,) array, optional

    Returns
    -------
    (4,) float64 or None when degenerate.
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if len(src) < 2:
        return None
    w = np.ones(len(src)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    ms = (w[:, None] * src).sum(0)
    md = (w[:, None] * dst).sum(0)
    s0 = src - ms
    d0 = dst - md
    var = float((w * (s0**2).sum(1)).sum())
    if var < 1e-9:
        return None
    a = float((w * (s0[:, 0] * d0[:, 0] + s0[:, 1] * d0[:, 1])).sum()) / var
    b = float((w * (s0[:, 0] * d0[:, 1] - s0[:, 1] * d0[:, 0])).sum()) / var
    scale = float(np.hypot(a, b))
    if scale <= 1e-9:
        return None
    angle = float(np.arctan2(b, a))
    t = md - scale * np.array(
        [
            np.cos(angle) * ms[0] - np.sin(angle) * ms[1],
            np.sin(angle) * ms[0] + np.cos(angle) * ms[1],
        ]
    )
    return np.array([t[0], t[1], angle, scale])


def to_similarity2d(sim: NDArray[np.floating]) -> Similarity2D:
    """Result value from a (4,) array (angle in degrees in (-180, 180])."""
    return Similarity2D(
        float(sim[0]), float(sim[1]), float(np.degrees(wrap_angle(float(sim[2])))), float(sim[3])
    )


def from_similarity2d(sim: Similarity2D) -> Array:
    """(4,) array from a result value."""
    return np.array([sim.x, sim.y, np.radians(sim.angle_deg), sim.scale])
