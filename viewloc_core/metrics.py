"""Pose evaluation metrics: the paper's g(L, T) and BOP's MSSD, MSPD, ADD-S.

References
----------
- Plagemann, Müller, Burgard, DAGM 2005, §5.1, Eq. 3: the localization
  accuracy ``g(L, T)``.
- Hodaň et al., "BOP: Benchmark for 6D Object Pose Estimation", ECCV 2018 and
  the BOP Challenge 2019 evaluation (``bop_toolkit_lib/pose_error.py``,
  ``scripts/eval_bop19_pose.py``): MSSD, MSPD, ADI (ADD-S), their correctness
  thresholds and the average recall.

Symmetries are passed as an ``(K, 4, 4)`` stack of object-frame rigid
transforms ``S`` (mm) that leave the object's appearance unchanged, the
identity included; the ground-truth pose ``T_gt`` is then equivalent to every
``T_gt @ S``. A continuous symmetry is passed already discretised (see
:func:`symmetry_transforms`).

"Recognized", defined once for the whole project
------------------------------------------------
- 2D (the paper's recognition, issue 3): the top detection's reference point,
  the image position ``(x, y)`` of the object origin returned by the 2D
  similarity, lies within ``0.1 ×`` the object's image diameter of the true
  projection of the object origin. The image diameter is
  ``focal_px × diameter_mm / z_gt`` (:func:`image_diameter_px`).
- 6D: the top detection's pose has MSSD ``< 0.1 ×`` the object diameter
  (symmetry-aware), the same test as BOP's MSSD recall at threshold 0.1.
A target without a detection is neither.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from viewloc_core.camera import Camera
from viewloc_core.errors import InvalidInputError
from viewloc_core.pose import Pose

Array = NDArray[np.float64]

#: The paper's weights (§5.1): δz and δxy in mm, δα in degrees.
F_Z = 1.0 / 250000.0
F_XY = 1.0 / 50000.0
F_ALPHA = 1.0 / 10000.0

#: BOP19 MSSD thresholds, fractions of the object diameter.
MSSD_THRESHOLDS_REL = np.round(np.arange(0.05, 0.51, 0.05), 4)
#: BOP19 MSPD thresholds in pixels for a 640 px wide image.
MSPD_THRESHOLDS_PX_640 = np.arange(5.0, 51.0, 5.0)
#: ADD-S correctness threshold, fraction of the object diameter.
ADDS_THRESHOLD_REL = 0.1
#: Reference-point tolerance of the 2D recognition, fraction of the image diameter.
RECOGNIZED_2D_REL = 0.1
#: MSSD tolerance of the 6D recognition, fraction of the object diameter.
RECOGNIZED_6D_REL = 0.1


def identity_symmetries() -> Array:
    """(1, 4, 4) float64: only the identity (an object without symmetry)."""
    return np.eye(4)[None]


def _as_symmetries(symmetries: NDArray[np.floating] | None) -> Array:
    if symmetries is None:
        return identity_symmetries()
    S = np.asarray(symmetries, dtype=np.float64)
    if S.ndim == 2:
        S = S[None]
    if S.ndim != 3 or S.shape[1:] != (4, 4) or len(S) == 0:
        raise InvalidInputError(
            f"symmetries must have shape (K, 4, 4), got {S.shape}", "symmetries"
        )
    return S


def symmetry_transforms(
    discrete: Sequence[NDArray[np.floating]] = (),
    continuous: Sequence[tuple[NDArray[np.floating], NDArray[np.floating]]] = (),
    step_deg: float = 1.0,
) -> Array:
    """All symmetry transforms of an object, BOP's ``get_symmetry_transformations``.

    Parameters
    ----------
    discrete : sequence of (4, 4) arrays
        Discrete symmetries (without the identity, which is always added).
    continuous : sequence of (axis (3,), offset (3,)) pairs
        Continuous rotational symmetries about ``axis`` through ``offset``
        (object frame, mm). At most one is supported, as in BOP.
    step_deg : float
        Discretisation step of the continuous symmetry in degrees.

    Returns
    -------
    (K, 4, 4) float64
        Identity first, then every discrete symmetry combined with every
        discretised rotation of the continuous one.
    """
    if len(continuous) > 1:
        raise InvalidInputError("at most one continuous symmetry is supported", "continuous")
    if step_deg <= 0:
        raise InvalidInputError("step_deg must be positive", "step_deg")
    discrete_all = [np.eye(4)] + [np.asarray(d, dtype=np.float64).reshape(4, 4) for d in discrete]
    cont = [np.eye(4)]
    if continuous:
        axis = np.asarray(continuous[0][0], dtype=np.float64)
        offset = np.asarray(continuous[0][1], dtype=np.float64)
        axis = axis / np.linalg.norm(axis)
        n = max(1, int(round(360.0 / step_deg)))
        for k in range(1, n):
            R = Rotation.from_rotvec(axis * np.radians(k * 360.0 / n)).as_matrix()
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = offset - R @ offset
            cont.append(T)
    out = [c @ d for d in discrete_all for c in cont]
    return np.stack(out)


def _gt_poses_under_symmetry(pose_gt: Pose, symmetries: Array) -> tuple[Array, Array]:
    """Rotations (K, 3, 3) and translations (K, 3) of ``T_gt @ S`` for each S."""
    R_sym = pose_gt.R_m2c[None] @ symmetries[:, :3, :3]
    t_sym = symmetries[:, :3, 3] @ pose_gt.R_m2c.T + pose_gt.t_m2c
    return R_sym, t_sym


def paper_deltas(
    pose_est: Pose, pose_gt: Pose, symmetries: NDArray[np.floating] | None = None
) -> tuple[float, float, float]:
    """δz (mm), δxy (mm) and δα (deg) of the paper's g, at the best symmetry.

    Parameters
    ----------
    pose_est, pose_gt : Pose
        Estimated (L) and true (T) object -> camera poses, mm.
    symmetries : (K, 4, 4) array or None
        Object symmetries incl. identity; None means none.

    Returns
    -------
    (dz_mm, dxy_mm, dalpha_deg)
        The deltas for the symmetry that minimises the paper's cost
        ``fz δz² + fxy δxy² + fα δα²``. δz is along the camera's z axis
        (viewing direction), δxy perpendicular to it.
    """
    S = _as_symmetries(symmetries)
    R_sym, t_sym = _gt_poses_under_symmetry(pose_gt, S)
    dt = pose_est.t_m2c[None] - t_sym
    dz = np.abs(dt[:, 2])
    dxy = np.linalg.norm(dt[:, :2], axis=1)
    R_rel = np.einsum("ji,kjl->kil", pose_est.R_m2c, R_sym)
    cos = np.clip((np.trace(R_rel, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    dalpha = np.degrees(np.arccos(cos))
    cost = F_Z * dz**2 + F_XY * dxy**2 + F_ALPHA * dalpha**2
    k = int(np.argmin(cost))
    # The arccos above loses precision near 0; recompute the winner exactly.
    dalpha_k = float(np.degrees(Rotation.from_matrix(_orthonormal(R_rel[k])).magnitude()))
    return float(dz[k]), float(dxy[k]), dalpha_k


def _orthonormal(R: Array) -> Array:
    U, _, Vt = np.linalg.svd(R)
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt)) or 1.0)])
    return U @ D @ Vt


def g_from_deltas(dz_mm: float, dxy_mm: float, dalpha_deg: float) -> float:
    """The paper's ``g = max{0, 1 − (fz δz² + fxy δxy² + fα δα²)}`` (Eq. 3)."""
    return float(max(0.0, 1.0 - (F_Z * dz_mm**2 + F_XY * dxy_mm**2 + F_ALPHA * dalpha_deg**2)))


def g_paper(pose_est: Pose, pose_gt: Pose, symmetries: NDArray[np.floating] | None = None) -> float:
    """Localization accuracy g(L, T) of the paper (§5.1, Eq. 3), symmetry-aware.

    Parameters
    ----------
    pose_est, pose_gt : Pose
        Estimated (L) and true (T) object -> camera poses, mm.
    symmetries : (K, 4, 4) array or None
        Object symmetries incl. identity; the cost is minimised over them.

    Returns
    -------
    float
        In [0, 1]; 1 is a perfect pose. 23 mm across, 230 mm along the line
        of sight and 15° give 0.755 (the paper's text rounds it to 0.80).
    """
    return g_from_deltas(*paper_deltas(pose_est, pose_gt, symmetries))


def mssd(
    pose_est: Pose,
    pose_gt: Pose,
    pts_obj: NDArray[np.floating],
    symmetries: NDArray[np.floating] | None = None,
) -> float:
    """Maximum Symmetry-aware Surface Distance (BOP), mm.

    ``min_S max_i |T_est x_i − T_gt S x_i|`` over model vertices ``x_i``.

    Parameters
    ----------
    pose_est, pose_gt : Pose
        Object -> camera poses, mm.
    pts_obj : (N, 3) array
        Model vertices, object frame, mm.
    symmetries : (K, 4, 4) array or None
        Object symmetries incl. identity.
    """
    S = _as_symmetries(symmetries)
    pts = _points(pts_obj)
    pts_est = pose_est.transform(pts)
    R_sym, t_sym = _gt_poses_under_symmetry(pose_gt, S)
    best = np.inf
    for R, t in zip(R_sym, t_sym, strict=True):
        e = float(np.max(np.linalg.norm(pts_est - (pts @ R.T + t), axis=1)))
        best = min(best, e)
    return best


def mspd(
    pose_est: Pose,
    pose_gt: Pose,
    pts_obj: NDArray[np.floating],
    camera: Camera,
    symmetries: NDArray[np.floating] | None = None,
) -> float:
    """Maximum Symmetry-aware Projection Distance (BOP), pixels.

    ``min_S max_i |π(T_est x_i) − π(T_gt S x_i)|`` with the camera's projection π.

    Parameters
    ----------
    pose_est, pose_gt : Pose
        Object -> camera poses, mm.
    pts_obj : (N, 3) array
        Model vertices, object frame, mm.
    camera : Camera
        Intrinsics used for both projections.
    symmetries : (K, 4, 4) array or None
        Object symmetries incl. identity.
    """
    S = _as_symmetries(symmetries)
    pts = _points(pts_obj)
    uv_est = camera.project(pose_est.transform(pts))
    R_sym, t_sym = _gt_poses_under_symmetry(pose_gt, S)
    best = np.inf
    for R, t in zip(R_sym, t_sym, strict=True):
        uv_gt = camera.project(pts @ R.T + t)
        best = min(best, float(np.max(np.linalg.norm(uv_est - uv_gt, axis=1))))
    return best


def add_s(pose_est: Pose, pose_gt: Pose, pts_obj: NDArray[np.floating]) -> float:
    """ADD-S (BOP's ADI), mm: mean distance from each true point to the nearest estimated one.

    Parameters
    ----------
    pose_est, pose_gt : Pose
        Object -> camera poses, mm.
    pts_obj : (N, 3) array
        Model vertices, object frame, mm.
    """
    pts = _points(pts_obj)
    tree = cKDTree(pose_est.transform(pts))
    dists, _ = tree.query(pose_gt.transform(pts), k=1)
    return float(np.mean(dists))


def _points(pts_obj: NDArray[np.floating]) -> Array:
    pts = np.asarray(pts_obj, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise InvalidInputError(f"pts_obj must have shape (N, 3), got {pts.shape}", "pts_obj")
    return pts


def mssd_thresholds_mm(diameter_mm: float) -> Array:
    """(10,) BOP19 MSSD thresholds 0.05..0.5 × diameter, mm."""
    return MSSD_THRESHOLDS_REL * float(diameter_mm)


def mspd_thresholds_px(image_width: int) -> Array:
    """(10,) BOP19 MSPD thresholds 5..50 px scaled by ``image_width / 640``."""
    return MSPD_THRESHOLDS_PX_640 * (float(image_width) / 640.0)


def recall_at(errors: NDArray[np.floating], thresholds: NDArray[np.floating]) -> Array:
    """Fraction of targets with error strictly below each threshold (BOP).

    Parameters
    ----------
    errors : (M,) array
        One error per target; ``inf`` or ``nan`` for a target without a
        detection, which counts as a miss at every threshold.
    thresholds : (T,) array or (M, T) array
        Common thresholds, or per-target thresholds (e.g. scaled by each
        target's diameter).

    Returns
    -------
    (T,) float64
        Recall per threshold; zeros when there are no targets.
    """
    e = np.asarray(errors, dtype=np.float64).reshape(-1)
    th = np.asarray(thresholds, dtype=np.float64)
    if len(e) == 0:
        return np.zeros(th.shape[-1])
    e = np.where(np.isnan(e), np.inf, e)
    ok = e[:, None] < (th if th.ndim == 2 else th[None, :])
    return ok.mean(axis=0).astype(np.float64)


def average_recall(errors: NDArray[np.floating], thresholds: NDArray[np.floating]) -> float:
    """Mean of :func:`recall_at` over the thresholds (BOP's AR for one error type)."""
    return float(np.mean(recall_at(errors, thresholds)))


def image_diameter_px(camera: Camera, pose_gt: Pose, diameter_mm: float) -> float:
    """Apparent size of the object in the image: ``focal_px × diameter / z``, pixels."""
    return float(camera.focal_px * diameter_mm / pose_gt.t_m2c[2])


def reference_point_error_px(xy_est: NDArray[np.floating], camera: Camera, pose_gt: Pose) -> float:
    """Distance (px) between an estimated origin position and the true projected origin."""
    uv_gt = camera.project(pose_gt.t_m2c[None])[0]
    return float(np.linalg.norm(np.asarray(xy_est, dtype=np.float64).reshape(2) - uv_gt))


def recognized_2d(
    xy_est: NDArray[np.floating] | None, camera: Camera, pose_gt: Pose, diameter_mm: float
) -> bool:
    """The 2D recognition test (module doc): reference point within 0.1 image diameter."""
    if xy_est is None:
        return False
    tol = RECOGNIZED_2D_REL * image_diameter_px(camera, pose_gt, diameter_mm)
    return reference_point_error_px(xy_est, camera, pose_gt) <= tol


def recognized_6d(mssd_mm: float | None, diameter_mm: float) -> bool:
    """The 6D recognition test (module doc): MSSD below 0.1 × diameter."""
    return mssd_mm is not None and bool(mssd_mm < RECOGNIZED_6D_REL * diameter_mm)
