"""How well a refined pose is pinned down: its largest rotation uncertainty.

A contour fit that found image edges along a whole outline fixes every
rotation of the part to a degree or so; one that found them along one side
only, or along an outline that looks the same turned (a rounded clutter
object taken for a smooth part, a clutter stick for a barbell's bar), leaves the
rotation free in some direction, and its Gauss-Newton covariance says so
(the figures that set the limit applied to it are at
:data:`viewloc_core.localize.MAX_ROTATION_STD_DEG`). The principal
deviation used here is at least as large as the largest of the three
camera axes' deviations, and does not depend on how the camera's axes lie.

A rotation about the axis of a part's continuous symmetry (a barbell seen
end-on) changes nothing in the image and is no uncertainty of the pose that
matters: the deviation is taken with that rotation held fixed.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from viewloc_core.pose import Pose
from viewloc_core.symmetry import Symmetries

F64 = NDArray[np.float64]


def rotation_std_deg(covariance_6x6: NDArray[np.floating], pose: Pose,
                     symmetries: Symmetries) -> float:
    """The largest standard deviation of the pose's rotation over all axes,
    degrees; with a continuous symmetry, over the axes perpendicular to it
    while the turn about it is held fixed.

    Parameters
    ----------
    covariance_6x6 : (6, 6) array
        Covariance of (rotation about camera x, y, z through the pose's
        origin, rad; translation of that origin along camera x, y, z, mm),
        as :attr:`viewloc_core.refine.RefinementResult.covariance_6x6`.
    pose : Pose
        The refined pose, object -> camera (its rotation turns the symmetry
        axis into the camera frame; the origin may be any point of the part).
    symmetries : Symmetries
        The part's symmetries in the pose's object frame.

    Returns
    -------
    float
        Degrees, >= 0; ``inf`` when the covariance could not be estimated
        (non-finite) or the fit does not constrain the rotation at all.
    """
    cov = np.asarray(covariance_6x6, dtype=np.float64)
    if cov.shape != (6, 6) or not np.all(np.isfinite(cov)):
        return math.inf
    if symmetries.continuous_axis is None:
        rotation_cov = cov[:3, :3]
    else:
        turn_fixed = _with_turn_fixed(cov, pose.R_m2c @ symmetries.continuous_axis)
        if turn_fixed is None:
            return math.inf
        rotation_cov = turn_fixed
    largest = float(np.linalg.eigvalsh(0.5 * (rotation_cov + rotation_cov.T))[-1])
    return math.degrees(math.sqrt(largest)) if largest > 0 else 0.0


def _with_turn_fixed(cov: F64, axis_cam: F64) -> F64 | None:
    """(2, 2) covariance of the rotations perpendicular to the symmetry axis
    (rad^2, in an orthonormal basis of that plane) given that the part is
    not turned about the axis; None when it cannot be computed.

    A turn about the axis (camera direction ``axis_cam``) through a point
    ``q`` moves the parameters along ``(ω, ω × (t - q))``: rotation about the
    origin ``t`` plus the translation that keeps ``q`` in place. The
    parameters with no rotation along ``ω`` (rotations perpendicular to it,
    every translation) are a complement of that direction wherever ``q``
    lies: the information restricted to them is the inverse of the
    conditional covariance, whose rotation block is returned.
    """
    omega = axis_cam / np.linalg.norm(axis_cam)
    # Two unit vectors perpendicular to the axis (camera frame).
    helper = np.eye(3)[int(np.argmin(np.abs(omega)))]
    u = np.cross(omega, helper)
    u /= np.linalg.norm(u)
    v = np.cross(omega, u)
    basis = np.zeros((6, 5))
    basis[:3, 0], basis[:3, 1] = u, v
    basis[3:, 2:] = np.eye(3)
    try:
        conditional = np.linalg.inv(basis.T @ np.linalg.inv(cov) @ basis)
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(conditional)):
        return None
    return np.asarray(conditional[:2, :2], dtype=np.float64)
