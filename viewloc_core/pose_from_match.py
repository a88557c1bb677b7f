"""6D pose from a 2D similarity match and back (paper §4.2, DESIGN.md §2 step 7).

A training view ``k`` is a camera with rotation ``R_v`` (object -> training
camera, :func:`viewloc_core.view_sphere.view_rotation`), the object origin on
its optical axis at distance ``d0`` (``t_v = [0, 0, d0]``) and focal length
``f_train`` pixels. Model-view coordinates ``p`` are training-image pixels
relative to the projection of the object origin. The 2D engine reports the
similarity ``(x, y, α, s)`` that maps ``p`` into the scene image
(:class:`viewloc_core.detection.Similarity2D`).

The paper inverts ``T4 T3 T2 T1``: a *virtual* camera that shares the scene
camera's centre but looks straight at the object (optical axis along the ray
``r`` through ``(x, y)``) sees the training view rotated in-plane by ``α`` and
scaled by ``s``, so

``d = d0 · (f_scene / f_train) / s``, ``t = d · r``,
``R = R_{z→r} · R_z(α) · R_v``.

Improvement over the paper: when the object is far off the optical axis, the
rotation from the virtual to the real camera is a homography that, at the
object, stretches and turns the image a little (about ``1/cos`` of the
off-axis angle). The engine fits a similarity, i.e. the conformal part of that
local map, so we divide the conformal part of the homography's Jacobian out of
``(α, s)`` before using them. This removes the first-order perspective error in
the in-plane angle and distance; what remains is the anisotropic part, which a
similarity cannot express (a few tenths of a degree at 20° off-axis for
compact objects, up to about a degree for long thin ones) and which the
contour refinement (:mod:`viewloc_core.refine`) removes.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numpy.typing import NDArray

from viewloc_core.camera import Camera
from viewloc_core.detection import Similarity2D
from viewloc_core.errors import InvalidInputError
from viewloc_core.pose import Pose, orthonormalize, reorthonormalized, rot_z, rotation_between

Array = NDArray[np.float64]

_Z = np.array([0.0, 0.0, 1.0])


@functools.lru_cache(maxsize=8192)
def _checked_rotation(raw: bytes) -> Array:
    """The orthonormalized rotation of a (3, 3) float64 matrix given by its
    bytes, checked; read-only.

    Cached: the poses of one localization come from a few dozen of a model's
    training views, each checked and orthonormalized (an SVD) once rather
    than in every call (a fifth of the pose's cost).
    """
    R_v = np.frombuffer(raw, np.float64).reshape(3, 3)
    if not np.all(np.isfinite(R_v)):
        raise InvalidInputError("R_view_m2c must be a finite (3, 3) rotation", "R_view_m2c")
    if abs(np.linalg.det(R_v) - 1.0) > 1e-3 or np.abs(R_v @ R_v.T - np.eye(3)).max() > 1e-3:
        raise InvalidInputError("R_view_m2c is not a rotation matrix", "R_view_m2c")
    R = orthonormalize(R_v)
    R.flags.writeable = False
    return R


def _check_inputs(R_view_m2c: NDArray[np.floating], d0_mm: float, f_train_px: float) -> Array:
    R_v = np.asarray(R_view_m2c, dtype=np.float64)
    if R_v.shape != (3, 3):
        raise InvalidInputError("R_view_m2c must be a finite (3, 3) rotation", "R_view_m2c")
    R = _checked_rotation(np.ascontiguousarray(R_v).tobytes())
    if not (math.isfinite(d0_mm) and d0_mm > 0):
        raise InvalidInputError(f"d0_mm must be positive, got {d0_mm}", "d0_mm")
    if not (math.isfinite(f_train_px) and f_train_px > 0):
        raise InvalidInputError(f"f_train_px must be positive, got {f_train_px}", "f_train_px")
    return R


_ROT90 = np.array([[0.0, -1.0], [1.0, 0.0]])
# Row-major vec of the similarity a·I + b·Rot90 as a function of (a, b).
_SIM_BASIS = np.array([[1.0, 0.0], [0.0, -1.0], [0.0, 1.0], [1.0, 0.0]])


def _virtual_to_image_jacobian(camera: Camera, R_z2r: Array) -> Array:
    """(2, 2) Jacobian of the virtual -> scene pixel map at the object origin.

    The virtual camera has focal ``camera.focal_px`` and looks along the ray;
    its pixel offsets ``q`` map to scene pixels through ``R_z2r`` and the scene
    camera (with its distortion). Central differences, because distortion
    makes the closed form long.
    """
    f = camera.focal_px
    h = 0.5
    q = np.array([[h, 0.0], [-h, 0.0], [0.0, h], [0.0, -h]])
    rays_virt = np.column_stack([q / f, np.ones(4)])
    uv = camera.project(rays_virt @ R_z2r.T)
    return np.column_stack([(uv[0] - uv[1]) / (2 * h), (uv[2] - uv[3]) / (2 * h)])


def _virtual_similarity_pinhole(
    camera: Camera, x_px: float, y_px: float, a_m: float, b_m: float,
) -> tuple[Array, Array, float, float]:
    """The ray, ``R_z2r`` and virtual similarity ``(a_v, b_v)`` of
    :func:`pose_from_similarity` for a camera without distortion and
    isotropic features, in scalar arithmetic.

    The same steps as the general path (:meth:`Camera.ray`,
    :func:`_virtual_to_image_jacobian`, :func:`_similarity_fit_operator`
    with the isotropic projection and the 2x2 solve): every rival start of
    a localization's pose fits comes through here (11 an image on the
    paper bench set, 29 on the hard one, more on LM-O's photos), and the
    small numpy calls made a pose cost 0.27-0.33 ms; 0.05 ms this way.
    For isotropic features the fit operator is the conformal part
    ``[[p, -q], [q, p]]`` of the Jacobian, so the solve is a complex
    division.

    Returns
    -------
    ray : (3,) float64
        Unit ray through ``(x_px, y_px)``, camera frame.
    R_z2r : (3, 3) float64
        Rotation taking the optical axis onto the ray.
    a_v, b_v : float
        The virtual camera's similarity, ``s (cos α, sin α)``.
    """
    rx = (x_px - camera.cx) / camera.fx
    ry = (y_px - camera.cy) / camera.fy
    norm = math.sqrt(rx * rx + ry * ry + 1.0)
    ray = np.array([rx / norm, ry / norm, 1.0 / norm])
    R_z2r = rotation_between(_Z, ray)
    # Central differences of the virtual -> scene pixel map at the origin
    # (as _virtual_to_image_jacobian), half a pixel each way.
    f = camera.focal_px
    h = 0.5
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R_z2r.tolist()

    def pixel(qx: float, qy: float) -> tuple[float, float]:
        vx, vy = qx / f, qy / f
        z = r20 * vx + r21 * vy + r22
        return ((r00 * vx + r01 * vy + r02) / z * camera.fx + camera.cx,
                (r10 * vx + r11 * vy + r12) / z * camera.fy + camera.cy)

    (u_px, v_px), (u_mx, v_mx) = pixel(h, 0.0), pixel(-h, 0.0)
    (u_py, v_py), (u_my, v_my) = pixel(0.0, h), pixel(0.0, -h)
    j00, j10 = (u_px - u_mx) / (2 * h), (v_px - v_mx) / (2 * h)
    j01, j11 = (u_py - u_my) / (2 * h), (v_py - v_my) / (2 * h)
    p, q = 0.5 * (j00 + j11), 0.5 * (j10 - j01)
    den = p * p + q * q
    return ray, R_z2r, (a_m * p + b_m * q) / den, (b_m * p - a_m * q) / den


def _similarity_fit_operator(J: Array, spread: Array | None) -> Array:
    """(2, 2) map from the virtual similarity (a, b) to the one the engine fits.

    The engine fits a similarity ``S`` to points whose true map is the affine
    ``J · S_v``; least squares over points with second moment ``C`` minimises
    ``tr((S - J S_v) C (S - J S_v)^T)``, which is linear in both. ``C = I``
    (isotropic features) keeps exactly the conformal part of ``J``.
    """
    P = _ISOTROPIC_PROJECTION if spread is None else _conformal_projection(spread)
    G = np.column_stack([J.reshape(4), (J @ _ROT90).reshape(4)])
    return P @ G


def _conformal_projection(C: Array) -> Array:
    """(2, 4) weighted least-squares projection of a row-major (2, 2) map onto
    the similarities (a, b), for points with second moment ``C``."""
    W = np.zeros((4, 4))
    W[:2, :2] = C
    W[2:, 2:] = C
    return np.linalg.solve(_SIM_BASIS.T @ W @ _SIM_BASIS, _SIM_BASIS.T @ W)


#: The projection for isotropic features (C = I), the usual case: computed once.
_ISOTROPIC_PROJECTION = _conformal_projection(np.eye(2))


def _check_spread(spread: NDArray[np.floating] | None) -> Array | None:
    if spread is None:
        return None
    C = np.asarray(spread, dtype=np.float64)
    if C.shape != (2, 2) or not np.all(np.isfinite(C)):
        raise InvalidInputError(
            "model_spread_px2 must be a finite (2, 2) matrix", "model_spread_px2"
        )
    C = 0.5 * (C + C.T)
    if np.linalg.eigvalsh(C)[0] <= 0:
        raise InvalidInputError("model_spread_px2 must be positive definite", "model_spread_px2")
    return C / np.trace(C)


def pose_from_similarity(
    similarity: Similarity2D,
    R_view_m2c: NDArray[np.floating],
    d0_mm: float,
    f_train_px: float,
    camera: Camera,
    *,
    ref_depth_mm: float = 0.0,
    model_spread_px2: NDArray[np.floating] | None = None,
) -> Pose:
    """6D pose of the object from a 2D match with a training view (paper §4.2).

    Parameters
    ----------
    similarity : Similarity2D
        Match ``(x, y, α, s)``: model-view pixels -> scene pixels; ``(x, y)`` is
        where the object origin appears in the scene image (distorted pixels
        when the camera has distortion).
    R_view_m2c : (3, 3) array
        Rotation object -> training camera of the best-fitting training view.
    d0_mm : float
        Distance of the training camera from the object origin, mm.
    f_train_px : float
        Focal length of the training camera, pixels.
    camera : Camera
        Scene camera; lens distortion is removed from the ray and from the
        local image map when coefficients are given.
    ref_depth_mm : float
        Mean depth of the model view's features relative to the object
        origin along the training optical axis (mm, positive = farther from
        the camera). The scale ``s`` is the magnification at that depth, not
        at the origin's; 0 (the paper's assumption) when unknown.
    model_spread_px2 : (2, 2) array or None
        Second moment of the model view's feature positions (model-view
        pixels, about their centroid). When given, the anisotropic part of
        the off-axis perspective is removed too; None assumes isotropic.

    Returns
    -------
    Pose
        Object -> scene camera, mm. Exact when the object is seen along the
        training view's direction and centred; off-centre the remaining error
        is second order in the off-axis angle (see module notes).
    """
    R_v = _check_inputs(R_view_m2c, d0_mm, f_train_px)
    spread = _check_spread(model_spread_px2)
    if not (math.isfinite(similarity.scale) and similarity.scale > 0):
        raise InvalidInputError(f"scale must be positive, got {similarity.scale}", "scale")
    xy = np.array([[similarity.x, similarity.y]], dtype=np.float64)
    if not np.all(np.isfinite(xy)) or not math.isfinite(similarity.angle_deg):
        raise InvalidInputError("similarity must be finite", "similarity")
    if not (math.isfinite(ref_depth_mm) and abs(ref_depth_mm) < d0_mm):
        raise InvalidInputError("ref_depth_mm must be finite and smaller than d0", "ref_depth_mm")
    a_m = similarity.scale * math.cos(math.radians(similarity.angle_deg))
    b_m = similarity.scale * math.sin(math.radians(similarity.angle_deg))
    if spread is None and not camera.has_distortion:
        ray, R_z2r, a_v, b_v = _virtual_similarity_pinhole(camera, similarity.x,
                                                           similarity.y, a_m, b_m)
    else:
        ray = camera.ray(xy)[0]
        R_z2r = rotation_between(_Z, ray)
        L = _similarity_fit_operator(_virtual_to_image_jacobian(camera, R_z2r), spread)
        a_v, b_v = (float(v) for v in np.linalg.solve(L, [a_m, b_m]))
    scale_virtual = math.hypot(a_v, b_v)
    alpha_virtual = math.atan2(b_v, a_v)
    # The magnification s holds at depth d0 + ref_depth in training and
    # d + ref_depth in the scene.
    ref_scene = (d0_mm + ref_depth_mm) * (camera.focal_px / f_train_px) / scale_virtual
    distance = ref_scene - ref_depth_mm
    if distance <= 0:
        raise InvalidInputError("scale too large for the training distance", "scale")
    R_m2c = R_z2r @ rot_z(alpha_virtual) @ R_v
    return Pose(reorthonormalized(R_m2c), distance * ray)


def similarity_from_pose(
    pose: Pose,
    R_view_m2c: NDArray[np.floating],
    d0_mm: float,
    f_train_px: float,
    camera: Camera,
    *,
    ref_depth_mm: float = 0.0,
    model_spread_px2: NDArray[np.floating] | None = None,
) -> Similarity2D:
    """The 2D similarity under which a training view appears at a given pose.

    Inverse of :func:`pose_from_similarity` (same keyword arguments): exact
    round trip when the pose's viewing direction (object origin -> camera,
    object frame) equals the training view's; otherwise the in-plane angle is
    that of the closest rotation about the line of sight.

    Parameters
    ----------
    pose : Pose
        Object -> scene camera, mm; the object origin must be in front (z > 0).
    R_view_m2c : (3, 3) array
        Rotation object -> training camera of the training view.
    d0_mm, f_train_px : float
        Training distance (mm) and focal length (px).
    camera : Camera
        Scene camera.
    ref_depth_mm, model_spread_px2
        As in :func:`pose_from_similarity`.

    Returns
    -------
    Similarity2D
        With ``angle_deg`` in (-180, 180].
    """
    R_v = _check_inputs(R_view_m2c, d0_mm, f_train_px)
    spread = _check_spread(model_spread_px2)
    t = pose.t_m2c
    distance = float(np.linalg.norm(t))
    if t[2] <= 0 or distance <= 0:
        raise InvalidInputError("object origin must be in front of the camera", "pose")
    if not (math.isfinite(ref_depth_mm) and abs(ref_depth_mm) < min(d0_mm, distance)):
        raise InvalidInputError("ref_depth_mm must be finite and smaller than d0", "ref_depth_mm")
    ray = t / distance
    R_z2r = rotation_between(_Z, ray)
    M = R_z2r.T @ pose.R_m2c @ R_v.T
    alpha_virtual = math.atan2(M[1, 0] - M[0, 1], M[0, 0] + M[1, 1])
    scale_virtual = (
        (camera.focal_px / f_train_px) * (d0_mm + ref_depth_mm) / (distance + ref_depth_mm)
    )
    L = _similarity_fit_operator(_virtual_to_image_jacobian(camera, R_z2r), spread)
    a_m, b_m = scale_virtual * (L @ [math.cos(alpha_virtual), math.sin(alpha_virtual)])
    xy = camera.project(t[None, :])[0]
    angle = math.degrees(math.atan2(b_m, a_m))
    if angle <= -180.0:
        angle += 360.0
    return Similarity2D(float(xy[0]), float(xy[1]), angle, float(math.hypot(a_m, b_m)))
