"""Rigid poses (object -> camera) and rotation helpers.

Convention (DESIGN.md §3, API.md): ``x_cam = R_m2c @ x_obj + t_m2c``, OpenCV
camera frame (x right, y down, z forward), lengths in mm. Quaternions are
``[w, x, y, z]`` with unit norm and ``w >= 0``. Euler angles ``euler_xyz_deg``
are extrinsic rotations about the fixed x, then y, then z axis, so that
``R = Rz(c) @ Ry(b) @ Rx(a)`` (SciPy's lowercase ``"xyz"``).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from viewloc_core.errors import InvalidInputError

Array = NDArray[np.float64]


def orthonormalize(R: NDArray[np.floating]) -> Array:
    """Nearest rotation matrix (Frobenius norm) to a (3, 3) matrix, det +1."""
    U, _, Vt = np.linalg.svd(np.asarray(R, dtype=np.float64))
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt)) or 1.0)])
    return U @ D @ Vt


_ONE_AND_HALF_I = 1.5 * np.eye(3)


def reorthonormalized(R: NDArray[np.floating]) -> Array:
    """A rotation matrix made orthonormal again after rounding.

    A product of rotations, or of a rotation and two reflections, is a
    rotation up to rounding: one Björck step ``R (3 I - RᵀR) / 2`` makes
    it orthonormal again at a fraction of the cost of
    :func:`orthonormalize`'s SVD, which is for matrices farther off.
    """
    return R @ (_ONE_AND_HALF_I - 0.5 * (R.T @ R))


def rot_z(angle_rad: float) -> Array:
    """(3, 3) rotation by ``angle_rad`` about +z (counter-clockwise seen from +z)."""
    c, s = np.cos(angle_rad), np.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rotation_between(a: NDArray[np.floating], b: NDArray[np.floating]) -> Array:
    """Smallest rotation taking direction ``a`` onto direction ``b``.

    The paper's ``T_{a,b}`` (§4.2): rotation about the axis perpendicular to
    both. For opposite vectors an arbitrary perpendicular axis is used.

    Parameters
    ----------
    a, b : (3,) array
        Non-zero vectors (need not be unit).

    Returns
    -------
    (3, 3) float64
        Rotation with ``R @ a/|a| == b/|b|``.
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    a = a / np.linalg.norm(a)
    b = b / np.linalg.norm(b)
    # Scalar arithmetic on the three components: the 6D pose of every 2D
    # match starts here (about ten per localization), and numpy's and
    # SciPy's call overheads made this 0.1 ms of the pose's 0.2 ms.
    ax, ay, az = float(a[0]), float(a[1]), float(a[2])
    bx, by, bz = float(b[0]), float(b[1]), float(b[2])
    vx, vy, vz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx
    s = math.sqrt(vx * vx + vy * vy + vz * vz)
    c = min(max(ax * bx + ay * by + az * bz, -1.0), 1.0)
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        perp = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(perp) < 1e-6:
            perp = np.cross(a, [0.0, 1.0, 0.0])
        perp /= np.linalg.norm(perp)
        return Rotation.from_rotvec(np.pi * perp).as_matrix()
    # About the unit axis k = v / s, with sin(t) = s and cos(t) = c.
    return _rodrigues(vx / s, vy / s, vz / s, c, s)


def _rodrigues(kx: float, ky: float, kz: float, cos_t: float, sin_t: float) -> Array:
    """(3, 3) rotation about the unit axis ``k`` by the angle ``t`` of the
    given cosine and sine: R = I + sin(t) K + (1 - cos(t)) K², K the
    cross-product matrix of ``k``."""
    w = 1.0 - cos_t
    s = sin_t
    return np.array([
        [1.0 - w * (ky * ky + kz * kz), w * kx * ky - s * kz, w * kx * kz + s * ky],
        [w * kx * ky + s * kz, 1.0 - w * (kx * kx + kz * kz), w * ky * kz - s * kx],
        [w * kx * kz - s * ky, w * ky * kz + s * kx, 1.0 - w * (kx * kx + ky * ky)],
    ])


def rotation_angle_deg(R_a: NDArray[np.floating], R_b: NDArray[np.floating]) -> float:
    """Angle in degrees of the relative rotation ``R_a^T R_b`` (0..180)."""
    R_rel = orthonormalize(np.asarray(R_a, dtype=np.float64).T @ np.asarray(R_b, dtype=np.float64))
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R_rel.tolist()
    # atan2 of the sine's and cosine's multiples, 2 sin θ = |R - Rᵀ| and
    # 2 cos θ = trace - 1, stays accurate near 0 and 180° where arccos of
    # the trace (or arcsin) loses half the digits; in scalars, because
    # SciPy's rotation object took 0.2 of this function's 0.26 ms (the
    # canonical pose of every fit of a symmetric part reads one angle per
    # element of its symmetry group).
    two_sin = math.sqrt((r21 - r12) ** 2 + (r02 - r20) ** 2 + (r10 - r01) ** 2)
    return math.degrees(math.atan2(two_sin, r00 + r11 + r22 - 1.0))


def rotation_about_axis(axis: NDArray[np.floating], angle_rad: float) -> Array:
    """(3, 3) rotation by ``angle_rad`` about a unit ``axis`` (right hand).

    Rodrigues' formula in scalars (as :func:`rotation_between`): SciPy's
    rotation object costs about 40 µs a call, and a symmetric part's
    canonical pose turns it about its axis for every fit.
    """
    kx, ky, kz = (float(v) for v in axis)
    return _rodrigues(kx, ky, kz, math.cos(angle_rad), math.sin(angle_rad))


@dataclass(frozen=True, slots=True)
class Pose:
    """Rigid transform from object (model) coordinates to camera coordinates.

    Attributes
    ----------
    R_m2c : (3, 3) float64
        Rotation, orthonormal with det +1.
    t_m2c : (3,) float64
        Translation in mm (the object origin in the camera frame).
    """

    R_m2c: Array
    t_m2c: Array

    def __post_init__(self) -> None:
        R = np.asarray(self.R_m2c, dtype=np.float64)
        t = np.asarray(self.t_m2c, dtype=np.float64).reshape(-1)
        if R.shape != (3, 3) or t.shape != (3,):
            raise InvalidInputError(
                f"pose needs R (3, 3) and t (3,), got {R.shape} and {t.shape}", "pose"
            )
        # ndarray.all, not np.all: poses are built in every refinement step
        # and np.all's dispatch costs more than the test.
        if not (np.isfinite(R).all() and np.isfinite(t).all()):
            raise InvalidInputError("pose must be finite", "pose")
        object.__setattr__(self, "R_m2c", R)
        object.__setattr__(self, "t_m2c", t)

    @classmethod
    def identity(cls) -> Pose:
        """The identity pose."""
        return cls(np.eye(3), np.zeros(3))

    @classmethod
    def from_matrix(cls, T: NDArray[np.floating]) -> Pose:
        """From a (4, 4) homogeneous matrix."""
        T_m2c = np.asarray(T, dtype=np.float64)
        return cls(T_m2c[:3, :3], T_m2c[:3, 3])

    @classmethod
    def from_quaternion(cls, q_wxyz: NDArray[np.floating], t_m2c: NDArray[np.floating]) -> Pose:
        """From a quaternion ``[w, x, y, z]`` (normalised here) and t in mm."""
        q = np.asarray(q_wxyz, dtype=np.float64)
        if q.shape != (4,) or not np.all(np.isfinite(q)) or np.linalg.norm(q) < 1e-12:
            raise InvalidInputError("quaternion must be 4 finite numbers, not all 0", "quaternion")
        R = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()
        return cls(R, np.asarray(t_m2c, dtype=np.float64))

    @classmethod
    def from_euler_xyz_deg(
        cls, angles_deg: NDArray[np.floating], t_m2c: NDArray[np.floating]
    ) -> Pose:
        """From extrinsic x-y-z Euler angles in degrees and t in mm."""
        R = Rotation.from_euler("xyz", np.asarray(angles_deg, dtype=np.float64), degrees=True)
        return cls(R.as_matrix(), np.asarray(t_m2c, dtype=np.float64))

    @property
    def matrix(self) -> Array:
        """(4, 4) homogeneous matrix."""
        T = np.eye(4)
        T[:3, :3] = self.R_m2c
        T[:3, 3] = self.t_m2c
        return T

    @property
    def quaternion_wxyz(self) -> Array:
        """(4,) unit quaternion ``[w, x, y, z]`` with ``w >= 0``."""
        x, y, z, w = Rotation.from_matrix(orthonormalize(self.R_m2c)).as_quat()
        q = np.array([w, x, y, z])
        return -q if q[0] < 0 else q

    @property
    def euler_xyz_deg(self) -> Array:
        """(3,) extrinsic x-y-z Euler angles in degrees.

        At gimbal lock (middle angle ±90°) the first and third angles are not
        unique; scipy then sets the third to zero, which still gives the
        rotation exactly.
        """
        rotation = Rotation.from_matrix(orthonormalize(self.R_m2c))
        with warnings.catch_warnings():
            # scipy warns at gimbal lock; the angles it returns are valid.
            warnings.filterwarnings("ignore", "Gimbal lock detected", UserWarning)
            return np.asarray(rotation.as_euler("xyz", degrees=True), dtype=np.float64)

    def inverse(self) -> Pose:
        """Camera -> object transform."""
        return Pose(self.R_m2c.T, -self.R_m2c.T @ self.t_m2c)

    def compose(self, other: Pose) -> Pose:
        """``self ∘ other``: apply ``other`` first, then ``self``."""
        return Pose(self.R_m2c @ other.R_m2c, self.R_m2c @ other.t_m2c + self.t_m2c)

    def transform(self, pts_obj: NDArray[np.floating]) -> Array:
        """Map (N, 3) object points (mm) to (N, 3) camera points (mm)."""
        pts = np.asarray(pts_obj, dtype=np.float64).reshape(-1, 3)
        return pts @ self.R_m2c.T + self.t_m2c
