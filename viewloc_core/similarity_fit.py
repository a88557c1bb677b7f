"""Greedy point-to-line fit of many 2D similarities to image edges, compiled.

The inner loop of :func:`viewloc_core.align.extend_many` (the alignment's
extension of every voted hypothesis, its final fits and the view search's
least-squares fits all run it): for each hypothesis and each pairing radius,
map the model's edge samples into the image, pair each with the nearest image
edge pixel (a table look-up) when it lies within the radius and has a similar
orientation, and solve the 4x4 normal equations of the point-to-line
distances for the similarity's linear parameters ``(s cos α, s sin α, x, y)``.

Written as explicit loops for numba: the same work as a batch of array
operations costs a few hundred numpy calls per image, each on a few thousand
elements, and was the largest share of the alignment's time. Sums run in
sample order, so results equal the array version's up to rounding.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import NDArray

F64 = NDArray[np.float64]


@njit(cache=True, nogil=True)
def _solve4(AtA: F64, Atb: F64) -> tuple[float, F64]:  # pragma: no cover - compiled
    """Determinant and solution of one 4x4 system (Gaussian elimination with
    partial pivoting, on copies); the solution is zeros when the determinant is 0."""
    M = AtA.copy()
    b = Atb.copy()
    det = 1.0
    x = np.zeros(4)
    for col in range(4):
        piv = col
        for r in range(col + 1, 4):
            if abs(M[r, col]) > abs(M[piv, col]):
                piv = r
        if M[piv, col] == 0.0:
            return 0.0, x
        if piv != col:
            for c in range(4):
                M[col, c], M[piv, c] = M[piv, c], M[col, c]
            b[col], b[piv] = b[piv], b[col]
            det = -det
        det *= M[col, col]
        for r in range(col + 1, 4):
            f = M[r, col] / M[col, col]
            for c in range(col, 4):
                M[r, c] -= f * M[col, c]
            b[r] -= f * b[col]
    for r in range(3, -1, -1):
        acc = b[r]
        for c in range(r + 1, 4):
            acc -= M[r, c] * x[c]
        x[r] = acc / M[r, r]
    return det, x


@njit(cache=True, nogil=True)
def fit_similarities(
    sims: F64, pts: F64, theta: F64, valid: NDArray[np.bool_],
    nearest_edge: NDArray[np.int32], edge_distance: NDArray[np.float32],
    edge_xy: NDArray[np.float32], edge_theta: NDArray[np.float32],
    radii: F64, tol_rad: float, robust: bool,
) -> F64:  # pragma: no cover - compiled
    """Greedy extension of H hypotheses (see :func:`viewloc_core.align.extend_many`).

    Parameters
    ----------
    sims : (H, 4) float64
        Initial model -> image similarities ``(x, y, angle_rad, scale)``.
    pts : (H, P, 2) float64
        Model edge samples of each hypothesis.
    theta : (H, P) float64
        Their orientations modulo π, radians.
    valid : (H, P) bool
        Real samples (not padding).
    nearest_edge : (h, w) int32
        Index of the nearest edge pixel of every image pixel.
    edge_distance : (h, w) float32
        Distance to it, pixels.
    edge_xy : (E, 2) float32
        Edge pixel positions, pixels.
    edge_theta : (E,) float32
        Their orientations modulo π, radians.
    radii : (R,) float64
        Pairing radius of each step, pixels.
    tol_rad : float
        Largest orientation difference of a pairing, radians.
    robust : bool
        Huber weights, the relative degeneracy test and stop at the first
        failed step (the final fit); otherwise unweighted, absolute test and a
        failed step is skipped (the quick screen).

    Returns
    -------
    (H, 4) float64
        The re-fitted similarities (a hypothesis keeps its last good one).
    """
    n_hyp, n_pts = theta.shape
    h, w = nearest_edge.shape
    out = sims.copy()
    AtA = np.empty((4, 4))
    Atb = np.empty(4)
    a = np.empty(4)
    for i in range(n_hyp):
        x0, y0, ang, sc = out[i, 0], out[i, 1], out[i, 2], out[i, 3]
        for radius in radii:
            c = sc * math.cos(ang)
            s = sc * math.sin(ang)
            AtA[:] = 0.0
            Atb[:] = 0.0
            used = 0
            for p in range(n_pts):
                if not valid[i, p]:
                    continue
                sx = pts[i, p, 0]
                sy = pts[i, p, 1]
                u = c * sx - s * sy + x0
                v = s * sx + c * sy + y0
                ui = int(np.rint(u))
                vi = int(np.rint(v))
                if ui < 0 or ui >= w or vi < 0 or vi >= h:
                    continue
                if np.float64(edge_distance[vi, ui]) > radius:
                    continue
                nn = nearest_edge[vi, ui]
                # np.float64, not float(): numba's float() keeps a float32 a
                # float32, and sin, cos and the sums would run in single precision.
                img_theta = np.float64(edge_theta[nn])
                dth = abs((theta[i, p] + ang - img_theta) % math.pi)
                dth = min(dth, math.pi - dth)
                if not dth < tol_rad:
                    continue
                nx = -math.sin(img_theta)
                ny = math.cos(img_theta)
                dx = np.float64(edge_xy[nn, 0])
                dy = np.float64(edge_xy[nn, 1])
                wgt = 1.0
                if robust:
                    resid = abs((u - dx) * nx + (v - dy) * ny)
                    if resid > 1.0:
                        wgt = 1.0 / max(resid, 1e-9)
                a[0] = nx * sx + ny * sy
                a[1] = -nx * sy + ny * sx
                a[2] = nx
                a[3] = ny
                rhs = nx * dx + ny * dy
                for r in range(4):
                    wa = wgt * a[r]
                    Atb[r] += wa * rhs
                    for q in range(4):
                        AtA[r, q] += wa * a[q]
                used += 1
            ok = used >= 6
            if ok:
                det, sol = _solve4(AtA, Atb)
                if robust:
                    trace = max(AtA[0, 0] + AtA[1, 1] + AtA[2, 2] + AtA[3, 3], 1e-12)
                    ok = abs(det) >= 1e-9 * trace**4
                else:
                    ok = abs(det) > 1e-9
            if ok:
                scale = math.hypot(sol[0], sol[1])
                ok = 0.5 * sc < scale < 2.0 * sc
                new_angle = math.atan2(sol[1], sol[0])
                if robust:
                    ok = ok and math.isfinite(sol[2]) and math.isfinite(sol[3]) and (
                        math.isfinite(new_angle) and math.isfinite(scale))
                if ok:
                    x0, y0, ang, sc = sol[2], sol[3], new_angle, scale
            if robust and not ok:
                break
        out[i, 0], out[i, 1], out[i, 2], out[i, 3] = x0, y0, ang, sc
    return out


def warm_up() -> None:
    """Compile (or load from numba's cache) the fit for the types the
    pipeline passes, so that the first request does not pay for it
    (about 3 s to compile, 0.3 s to load)."""
    fit_similarities(np.zeros((1, 4)), np.zeros((1, 1, 2)), np.zeros((1, 1)),
                     np.zeros((1, 1), np.bool_), np.zeros((1, 1), np.int32),
                     np.zeros((1, 1), np.float32), np.zeros((1, 2), np.float32),
                     np.zeros(1, np.float32), np.ones(1), 0.1, True)
