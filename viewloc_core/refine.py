"""Contour-based 6D pose refinement against image edges (paper §5.2, DESIGN.md §2 step 8).

The paper's "scene-based tracking", done the way edge-based trackers do it
(RAPiD, Drummond & Cipolla; sparse contour points as in SRT3D/M3T):

1. take the precomputed contour points of the view nearest to the current
   pose (:class:`viewloc_core.contour_model.ContourModel`), project them and
   their normal directions with the scene camera (lens distortion applied, so
   the image is never undistorted);
2. search along each 2D normal, ``±search_px`` pixels on the current pyramid
   level, for a local maximum of the image gradient component along the
   normal; sign-agnostic (a dark part on a light background and the reverse
   both match); a candidate's gradient must be mostly along the normal, and
   nearer candidates are preferred (Gaussian prior on the offset);
3. robust Gauss-Newton (Tukey weights, scale from the MAD) on the point-to-
   line residuals ``n·(π(X) - q)`` over 6 parameters: a rotation about the
   object origin and a translation, both in camera axes;
4. iterate; coarse to fine over an image pyramid (larger capture range at the
   coarse levels, full precision at the finest).

Colour images: the gradient is taken per channel and, per pixel, the channel
with the largest gradient magnitude is kept (an edge between two colours of
equal brightness vanishes in grey). Uncertainty: the inverse Gauss-Newton
Hessian times the robust residual variance at the final pose; neighbouring
contour residuals are correlated, so it is a lower bound on the true spread
(tests measure the ratio).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from viewloc_core.camera import Camera
from viewloc_core.contour_model import ContourModel
from viewloc_core.errors import InvalidImageError, InvalidInputError
from viewloc_core.pose import Pose, orthonormalize

Array = NDArray[np.float64]

_TUKEY_C = 4.685


@dataclass(frozen=True, slots=True, eq=False)
class EdgePyramid:
    """Image gradients on a pyramid, shared by every detection in one image.

    Attributes
    ----------
    gradients : list of (H_l, W_l, 2) float32
        ``(∂I/∂x, ∂I/∂y)`` per level, level 0 full resolution, each next level
        half the size; intensities scaled to [0, 1], Sobel divided by 8 so the
        unit is intensity per pixel.
    width, height : int
        Size of level 0.
    """

    gradients: list[NDArray[np.float32]]
    width: int
    height: int

    @property
    def levels(self) -> int:
        """Number of pyramid levels."""
        return len(self.gradients)


def _as_float_image(image: NDArray[np.generic]) -> NDArray[np.float32]:
    arr = np.asarray(image)
    if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[2] not in (1, 3, 4)):
        raise InvalidImageError(f"image must be (H, W) or (H, W, 3), got {arr.shape}", "image")
    if arr.shape[0] < 8 or arr.shape[1] < 8:
        raise InvalidImageError("image is smaller than 8x8 pixels", "image")
    if arr.dtype == np.uint8:
        scale = 1.0 / 255.0
    elif arr.dtype == np.uint16:
        scale = 1.0 / 65535.0
    elif np.issubdtype(arr.dtype, np.floating):
        scale = 1.0
    else:
        raise InvalidImageError(f"image dtype must be uint8 or uint16, got {arr.dtype}", "image")
    out: NDArray[np.float32] = np.asarray(arr, dtype=np.float32) * np.float32(scale)
    if out.ndim == 3:
        out = out[:, :, :3] if out.shape[2] >= 3 else out[:, :, 0]
    return np.ascontiguousarray(out)


def _gradient(img: NDArray[np.float32]) -> NDArray[np.float32]:
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    if img.ndim == 3:
        # Per pixel the channel with the strongest edge.
        mag = gx * gx + gy * gy
        best = np.argmax(mag, axis=2)[..., None]
        gx = np.take_along_axis(gx, best, axis=2)[..., 0]
        gy = np.take_along_axis(gy, best, axis=2)[..., 0]
    return np.dstack([gx, gy])


def prepare_edges(image: NDArray[np.generic], levels: int = 3) -> EdgePyramid:
    """Gradient pyramid of an image (grey or colour, uint8 or uint16).

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array
        uint8 or uint16 (float in [0, 1] also accepted).
    levels : int
        1..5 pyramid levels (each halves the size).

    Returns
    -------
    EdgePyramid
        About 3-4 ms for a 640x480 colour image on this machine.
    """
    if not 1 <= levels <= 5:
        raise InvalidInputError(f"levels must be in 1..5, got {levels}", "levels")
    img = _as_float_image(image)
    grads = []
    current = img
    for level in range(levels):
        if level > 0:
            current = np.asarray(cv2.pyrDown(current), dtype=np.float32)
        grads.append(_gradient(current))
        if min(current.shape[:2]) < 16:
            break
    return EdgePyramid(grads, int(img.shape[1]), int(img.shape[0]))


@dataclass(frozen=True, slots=True)
class RefineOptions:
    """Settings of :func:`refine_pose`.

    Attributes
    ----------
    levels : int
        Pyramid levels used (coarsest first). Two by default: on a third
        level the two faces of thin plates merge into one edge and pull the
        fit away (measured on an L-bracket, 8 mm plates at 600 mm).
    search_px : tuple of int
        Half-length of the search along the normal on each level, in that
        level's pixels, finest level first.
    iterations : tuple of int
        Maximum Gauss-Newton iterations per level, finest level first.
    min_gradient : float
        Weakest gradient (intensity per pixel, intensities in [0, 1]) taken
        as an edge.
    max_angle_deg : float
        Largest angle between the image gradient and the contour normal.
    inlier_px : float
        A contour point is an inlier when an edge lies within this many
        full-resolution pixels of its final projection.
    tol_rot_deg, tol_trans_mm : float
        Convergence: the last update at the finest level is smaller.
    shift_search_px : float
        Half-width (full-resolution pixels) of the exhaustive 2D shift search
        run before Gauss-Newton; 0 switches it off.
    measure_chance : bool
        Measure the chance rate and support of the final pose (about a
        millisecond; quick checks that only compare inlier fractions skip it).
    """

    levels: int = 2
    search_px: tuple[int, ...] = (8, 4)
    iterations: tuple[int, ...] = (12, 4)
    min_gradient: float = 0.02
    max_angle_deg: float = 35.0
    inlier_px: float = 2.0
    tol_rot_deg: float = 0.01
    tol_trans_mm: float = 0.02
    shift_search_px: float = 16.0
    measure_chance: bool = True


@dataclass(frozen=True, slots=True, eq=False)
class RefinementResult:
    """Outcome of :func:`refine_pose`.

    Attributes
    ----------
    pose : Pose
        Refined object -> camera pose (the initial pose when it failed).
    converged : bool
        The finest level's updates fell below the tolerances and enough
        contour points matched.
    iterations : int
        Gauss-Newton iterations run over all levels.
    mean_residual_px : float
        Mean absolute residual of the inliers at the final pose, pixels.
    inlier_fraction : float
        Share of the projected (in-image) contour points with an image edge
        within ``inlier_px`` of them at the final pose: a verification score.
    covariance_6x6 : (6, 6) float64
        Covariance of (rotation about camera x, y, z through the object
        origin in rad, translation of the object origin along camera x, y, z
        in mm). Infinite diagonal when it could not be estimated.
    pose_std : (6,) float64
        Square roots of its diagonal: rotation in degrees, translation in mm.
    chance_fraction : float
        Inlier fraction the same contour reaches at nearby wrong places (the
        projection shifted sideways): how often image edges confirm a contour
        point by chance here, high in texture and clutter.
    support : float
        Log-likelihood ratio object vs. clutter of the contour evidence, per
        pixel of contour length: each matched point adds log(q / b), each
        unmatched one log((1 - q) / (1 - b)), with q the rate at the true
        pose and b the chance rate, weighted by the contour length it stands
        for. Longer confirmed outlines score higher, so a view that explains
        only part of the object (one plate of a barbell seen end-on) loses
        against one that explains all of it.
    """

    pose: Pose
    converged: bool
    iterations: int
    mean_residual_px: float
    inlier_fraction: float
    covariance_6x6: Array = field(default_factory=lambda: np.full((6, 6), np.inf))
    pose_std: Array = field(default_factory=lambda: np.full(6, np.inf))
    chance_fraction: float = 1.0
    support: float = -math.inf

    @property
    def score(self) -> float:
        """Inlier fraction corrected for chance, in [0, 1] (Cohen's kappa form)."""
        b = min(self.chance_fraction, 0.95)
        return float(np.clip((self.inlier_fraction - b) / (1.0 - b), 0.0, 1.0))


@dataclass(frozen=True, slots=True)
class _Matches:
    J: Array  # (M, 6) residual Jacobian, full-res pixels per (rad, mm)
    r: Array  # (M,) residuals, full-res pixels
    n_projected: int


def _project_view(
    pose: Pose, camera: Camera, model: ContourModel, margin_px: float
) -> tuple[Array, Array, Array] | None:
    """Projected contour points (N, 2), unit 2D normals (N, 2), camera points (N, 3)."""
    pts_obj, nrm_obj = model.view_points(model.nearest_view(pose))
    if len(pts_obj) == 0:
        return None
    X = pts_obj.astype(np.float64) @ pose.R_m2c.T + pose.t_m2c
    front = X[:, 2] > 1.0
    # A step of about a pixel along the stored 3D normal gives the 2D normal.
    eps = (X[:, 2] / camera.focal_px)[:, None]
    X2 = X + eps * (nrm_obj.astype(np.float64) @ pose.R_m2c.T)
    uv = camera.project(X[front])
    uv2 = camera.project(X2[front])
    X = X[front]
    d = uv2 - uv
    norm = np.linalg.norm(d, axis=1)
    ok = (
        (norm > 1e-6)
        & (uv[:, 0] >= margin_px) & (uv[:, 0] <= camera.width - 1 - margin_px)
        & (uv[:, 1] >= margin_px) & (uv[:, 1] <= camera.height - 1 - margin_px)
    )
    if not np.any(ok):
        return None
    return uv[ok], d[ok] / norm[ok, None], X[ok]


def _search(
    grad: NDArray[np.float32],
    uv_l: Array,
    n2: Array,
    search: int,
    min_gradient: float,
    cos_max: float,
) -> tuple[NDArray[np.bool_], Array]:
    """Edge offsets along the normals on one level: found (N,), offset (N,) level px."""
    ks = np.arange(-search, search + 1, dtype=np.float64)
    pos = uv_l[:, None, :] + ks[None, :, None] * n2[:, None, :]
    mapx = pos[..., 0].astype(np.float32)
    mapy = pos[..., 1].astype(np.float32)
    g = cv2.remap(grad, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                  borderValue=0)
    along = np.abs(g[..., 0] * n2[:, None, 0] + g[..., 1] * n2[:, None, 1])
    mag = np.sqrt(g[..., 0] ** 2 + g[..., 1] ** 2)
    score = np.where((along >= min_gradient) & (along >= cos_max * mag), along, 0.0)
    left = np.concatenate([np.zeros((len(score), 1)), score[:, :-1]], axis=1)
    right = np.concatenate([score[:, 1:], np.zeros((len(score), 1))], axis=1)
    peak = (score > 0) & (score >= left) & (score >= right)
    # A maximum at the end of the search line is only the slope of an edge
    # beyond it.
    peak[:, 0] = False
    peak[:, -1] = False
    sigma = max(1.0, search / 3.0)
    prior = np.exp(-0.5 * (ks / sigma) ** 2)
    weighted = np.where(peak, score * prior[None, :], 0.0)
    best = np.argmax(weighted, axis=1)
    rows = np.arange(len(best))
    found = weighted[rows, best] > 0
    s0 = score[rows, best]
    sl = np.where(best > 0, along[rows, np.maximum(best - 1, 0)], s0)
    sr = np.where(best < len(ks) - 1, along[rows, np.minimum(best + 1, len(ks) - 1)], s0)
    denom = sl - 2 * s0 + sr
    sub = np.where(np.abs(denom) > 1e-12, 0.5 * (sl - sr) / np.where(denom == 0, 1, denom), 0.0)
    offset = ks[best] + np.clip(sub, -0.5, 0.5)
    return found, offset


def _matches(
    pose: Pose,
    camera: Camera,
    model: ContourModel,
    edges: EdgePyramid,
    level: int,
    search: int,
    options: RefineOptions,
) -> _Matches | None:
    proj = _project_view(pose, camera, model, margin_px=1.0)
    if proj is None:
        return None
    uv, n2, X = proj
    f = 2.0**level
    uv_l = (uv + 0.5) / f - 0.5
    found, offset = _search(edges.gradients[level], uv_l, n2, search, options.min_gradient,
                            math.cos(math.radians(options.max_angle_deg)))
    if not np.any(found):
        return _Matches(np.zeros((0, 6)), np.zeros(0), len(uv))
    uv, n2, X, offset = uv[found], n2[found], X[found], offset[found]
    # The matched edge lies offset·f full-res pixels along n2 from the
    # projection; the residual n·(π(X) - q) is minus that.
    r = -offset * f
    x, y, z = X[:, 0], X[:, 1], X[:, 2]
    # dπ/dX of the pinhole part (distortion is a small, smooth correction).
    a = n2[:, 0] * camera.fx / z
    b = n2[:, 1] * camera.fy / z
    c = -(a * x + b * y) / z
    dres_dX = np.column_stack([a, b, c])  # (M, 3)
    P = X - pose.t_m2c  # rotation about the object origin: δX = ω × P + δt
    J_rot = np.cross(P, dres_dX)  # n·J_π·(ω × P) = ω · (P × (J_πᵀ n))
    J = np.column_stack([J_rot, dres_dX])
    return _Matches(J, r, len(uv_l))


def _tukey_weights(r: Array, min_scale: float) -> tuple[Array, float]:
    mad = float(np.median(np.abs(r - np.median(r))))
    scale = max(1.4826 * mad, min_scale)
    u = r / (_TUKEY_C * scale)
    w = np.where(np.abs(u) < 1.0, (1.0 - u * u) ** 2, 0.0)
    return w, scale


def _apply(pose: Pose, delta: Array) -> Pose:
    # cv2.Rodrigues: the same rotation vector -> matrix as scipy's, ~20x faster
    # on one vector (this runs once per Gauss-Newton step).
    dR, _ = cv2.Rodrigues(np.asarray(delta[:3], dtype=np.float64).reshape(3, 1))
    return Pose(orthonormalize(dR @ pose.R_m2c), pose.t_m2c + delta[3:])


def refine_pose(
    image: NDArray[np.generic] | EdgePyramid,
    camera: Camera,
    pose_init: Pose,
    contour_model: ContourModel,
    options: RefineOptions | None = None,
) -> RefinementResult:
    """Fit all 6 DoF so the part's visible contours meet the image edges.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8/uint16 array, or EdgePyramid
        The scene image, or its :func:`prepare_edges` pyramid (share it
        between detections in one image).
    camera : Camera
        Scene camera; its size must match the image; distortion is applied
        when projecting (the image is used as it is).
    pose_init : Pose
        Starting pose (e.g. from :func:`viewloc_core.pose_from_match.pose_from_similarity`);
        capture range about ±16 px of shift (exhaustive search), a few
        degrees of rotation and a few % of depth.
    contour_model : ContourModel
    options : RefineOptions or None
        Defaults when None.

    Returns
    -------
    RefinementResult
        Never raises for a failed fit: ``converged`` is False and the pose
        is the best one reached (the initial one if nothing matched).
    """
    opts = options or RefineOptions()
    edges = image if isinstance(image, EdgePyramid) else prepare_edges(image, opts.levels)
    if edges.width != camera.width or edges.height != camera.height:
        raise InvalidInputError(
            f"image is {edges.width}x{edges.height} but the camera is "
            f"{camera.width}x{camera.height}", "camera"
        )
    n_levels = min(opts.levels, edges.levels, len(opts.search_px), len(opts.iterations))
    pose = _align_shift(pose_init, camera, contour_model, edges, min(1, n_levels - 1), opts)
    iterations = 0
    last_step = (math.inf, math.inf)
    for level in range(n_levels - 1, -1, -1):
        search = int(opts.search_px[level])
        last_step = (math.inf, math.inf)
        for _ in range(int(opts.iterations[level])):
            m = _matches(pose, camera, contour_model, edges, level, search, opts)
            if m is None or len(m.r) < 6:
                break
            w, _ = _tukey_weights(m.r, min_scale=0.5 * 2.0**level)
            if np.count_nonzero(w) < 6:
                break
            Jw = m.J * w[:, None]
            H = m.J.T @ Jw
            g = Jw.T @ m.r
            # Levenberg damping keeps a poorly constrained direction (e.g.
            # depth of a small part) from jumping.
            H_damped = H + 1e-3 * np.diag(np.diag(H)) + 1e-9 * np.eye(6)
            try:
                delta = -np.linalg.solve(H_damped, g)
            except np.linalg.LinAlgError:
                break
            if not np.all(np.isfinite(delta)):
                break
            pose = _apply(pose, np.asarray(delta, dtype=np.float64))
            iterations += 1
            last_step = (math.degrees(float(np.linalg.norm(delta[:3]))),
                         float(np.linalg.norm(delta[3:])))
            if last_step[0] < opts.tol_rot_deg and last_step[1] < opts.tol_trans_mm:
                break
            # After the first levels the search can shrink as the pose settles.
            if level == 0:
                search = max(3, min(search, int(math.ceil(4 * float(np.median(np.abs(m.r))) + 2))))
    return _final(pose, camera, contour_model, edges, opts, iterations, last_step)


def _align_shift(
    pose: Pose, camera: Camera, model: ContourModel, edges: EdgePyramid, level: int,
    opts: RefineOptions,
) -> Pose:
    """Move the pose sideways by the 2D image shift that best fits the edges.

    Gauss-Newton with a per-point nearest-edge search locks onto the wrong
    one of two close parallel edges (the two faces of a thin plate) when the
    start is shifted by more than half their spacing. A small exhaustive
    search over 2D shifts of the whole projected contour (sum of the image
    gradient along each contour normal, as in chamfer matching) is immune to
    that and costs about a millisecond.
    """
    proj = _project_view(pose, camera, model, margin_px=1.0)
    if proj is None or opts.shift_search_px <= 0:
        return pose
    uv, n2, X = proj
    f = 2.0**level
    uv_l = (uv + 0.5) / f - 0.5
    rad = max(1, int(math.ceil(opts.shift_search_px / f)))
    grid = np.arange(-rad, rad + 1, dtype=np.float64)
    sx, sy = np.meshgrid(grid, grid)
    shifts = np.column_stack([sx.ravel(), sy.ravel()])  # (S, 2)
    pos = uv_l[None, :, :] + shifts[:, None, :]
    g = cv2.remap(edges.gradients[level], pos[..., 0].astype(np.float32),
                  pos[..., 1].astype(np.float32), cv2.INTER_LINEAR,
                  borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    along = np.abs(g[..., 0] * n2[None, :, 0] + g[..., 1] * n2[None, :, 1])
    # Saturate so a few very strong clutter edges cannot outvote the outline.
    score = np.minimum(along, 4.0 * opts.min_gradient).sum(axis=1)
    dist2 = (shifts**2).sum(axis=1)
    # Prefer the smaller shift among (near) ties.
    best = int(np.argmax(score - 1e-6 * dist2))
    if score[best] <= score[int(np.argmin(dist2))] * 1.02:
        return pose
    shift_px = shifts[best] * f
    z = float(pose.t_m2c[2])
    delta_t = np.array([shift_px[0] * z / camera.fx, shift_px[1] * z / camera.fy, 0.0])
    return Pose(pose.R_m2c, pose.t_m2c + delta_t)


def _final(
    pose: Pose,
    camera: Camera,
    model: ContourModel,
    edges: EdgePyramid,
    opts: RefineOptions,
    iterations: int,
    last_step: tuple[float, float],
) -> RefinementResult:
    """Inliers, residuals and covariance at the final pose (finest level)."""
    search = max(2, int(math.ceil(opts.inlier_px)) + 1)
    m = _matches(pose, camera, model, edges, 0, search, opts)
    if m is None or m.n_projected == 0:
        return RefinementResult(pose, False, iterations, math.inf, 0.0)
    inl = np.abs(m.r) <= opts.inlier_px
    fraction = float(np.count_nonzero(inl)) / m.n_projected
    chance, support = 1.0, -math.inf
    if opts.measure_chance:
        chance, spacing_px = _chance_fraction(pose, camera, model, edges, search, opts)
        support = _support(int(np.count_nonzero(inl)), m.n_projected, chance, spacing_px)
    if np.count_nonzero(inl) < 6:
        return RefinementResult(pose, False, iterations, math.inf, fraction,
                                chance_fraction=chance, support=support)
    r, J = m.r[inl], m.J[inl]
    w, _ = _tukey_weights(r, min_scale=0.25)
    H = J.T @ (J * w[:, None])
    dof = max(float(w.sum()) - 6.0, 1.0)
    sigma2 = float((w * r * r).sum()) / dof
    try:
        cov = sigma2 * np.linalg.inv(H)
    except np.linalg.LinAlgError:
        cov = np.full((6, 6), np.inf)
    diag = np.diag(cov)
    std = np.asarray(np.sqrt(np.where(diag >= 0, diag, np.inf)), dtype=np.float64)
    std[:3] = np.degrees(std[:3])
    converged = (
        last_step[0] < 10 * opts.tol_rot_deg
        and last_step[1] < 10 * opts.tol_trans_mm
        and fraction >= 0.3
    )
    return RefinementResult(pose, bool(converged), iterations,
                            float(np.abs(r).mean()), fraction,
                            np.asarray(cov, dtype=np.float64), std, chance, support)


#: Sideways shifts (full-resolution px) at which the chance rate is measured:
#: far enough that the true edges fall outside the inlier band, near enough
#: to see the same clutter.
_CHANCE_SHIFTS_PX = np.array([[9.0, 4.0], [-4.0, 9.0], [-9.0, -4.0], [4.0, -9.0]])

#: Rate at which contour points of a correct pose find their edge (measured:
#: median 0.90, 10th percentile 0.79 on the paper set at the true poses).
_Q_TRUE = 0.85


def _chance_fraction(
    pose: Pose, camera: Camera, model: ContourModel, edges: EdgePyramid, search: int,
    opts: RefineOptions,
) -> tuple[float, float]:
    """Inlier fraction of the contour shifted to nearby wrong places, and the
    median spacing of its projected points (px)."""
    proj = _project_view(pose, camera, model, margin_px=1.0)
    if proj is None or len(proj[0]) < 2:
        return 1.0, 0.0
    uv, n2, _ = proj
    # Contour points are not stored in order along the contour: the distance
    # to the nearest other point is their spacing.
    nn_dist, _ = cKDTree(uv).query(uv, k=2)
    spacing = float(np.median(nn_dist[:, 1]))
    cos_max = math.cos(math.radians(opts.max_angle_deg))
    rates = []
    for shift in _CHANCE_SHIFTS_PX:
        uv_s = uv + shift
        ok = ((uv_s[:, 0] >= 1) & (uv_s[:, 0] <= camera.width - 2)
              & (uv_s[:, 1] >= 1) & (uv_s[:, 1] <= camera.height - 2))
        if np.count_nonzero(ok) < 6:
            continue
        found, offset = _search(edges.gradients[0], uv_s[ok], n2[ok], search,
                                opts.min_gradient, cos_max)
        rates.append(np.count_nonzero(found & (np.abs(offset) <= opts.inlier_px)) / len(uv_s[ok]))
    chance = float(np.mean(rates)) if rates else 1.0
    return chance, spacing


def _support(n_inliers: int, n_projected: int, chance: float, spacing_px: float) -> float:
    """Length-weighted log-likelihood ratio of the contour evidence (see RefinementResult)."""
    b = float(np.clip(chance, 0.02, 0.8))
    q = _Q_TRUE
    n_out = n_projected - n_inliers
    llr = n_inliers * math.log(q / b) + n_out * math.log((1.0 - q) / (1.0 - b))
    return float(llr * spacing_px)
