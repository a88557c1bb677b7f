"""The largest rotation uncertainty of a refined pose, symmetry-aware."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from viewloc_core.pose import Pose
from viewloc_core.pose_determinacy import rotation_std_deg
from viewloc_core.symmetry import Symmetries

NONE = Symmetries.none()
ABOUT_Z = Symmetries(np.eye(4)[None], np.array([0.0, 0.0, 1.0]), np.zeros(3))


def _pose(R: np.ndarray | None = None) -> Pose:
    return Pose(np.eye(3) if R is None else R, np.array([10.0, -20.0, 600.0]))


def _turn_twist(pose: Pose, axis_obj: np.ndarray, point_obj: np.ndarray) -> np.ndarray:
    """The (rotation, translation) parameter direction of a turn about the
    object-frame line through ``point_obj`` along ``axis_obj``."""
    omega = pose.R_m2c @ axis_obj
    q = pose.R_m2c @ point_obj + pose.t_m2c
    return np.concatenate([omega, np.cross(omega, pose.t_m2c - q)])


def test_without_symmetry_it_is_the_largest_principal_deviation():
    sd_rad = np.radians([1.0, 4.0, 2.0])
    cov = np.diag([*sd_rad**2, 1.0, 1.0, 9.0])
    assert math.isclose(rotation_std_deg(cov, _pose(), NONE), 4.0, rel_tol=1e-9)
    # A correlated pair: the principal deviation exceeds either axis's own.
    cov[0, 1] = cov[1, 0] = 0.9 * sd_rad[0] * sd_rad[1]
    assert rotation_std_deg(cov, _pose(), NONE) > 4.0


def test_unknown_covariance_is_infinitely_uncertain():
    assert rotation_std_deg(np.full((6, 6), np.inf), _pose(), NONE) == math.inf
    assert rotation_std_deg(np.full((6, 6), np.inf), _pose(), ABOUT_Z) == math.inf


def test_the_turn_about_a_symmetry_axis_is_no_uncertainty():
    # A part symmetric about its z axis through (0, 5, 0) mm, seen tilted:
    # the contour constrains every direction but that turn, weakly or not at all.
    R = Rotation.from_euler("xyz", [40.0, -25.0, 10.0], degrees=True).as_matrix()
    pose = _pose(R)
    sym = Symmetries(np.eye(4)[None], np.array([0.0, 0.0, 1.0]), np.array([0.0, 5.0, 0.0]))
    rng = np.random.default_rng(3)
    twist = _turn_twist(pose, sym.continuous_axis, sym.continuous_offset)
    twist /= np.linalg.norm(twist)
    # Measurements: rows of a Jacobian that cannot see the turn.
    J = rng.normal(size=(200, 6)) * np.array([300.0, 300.0, 300.0, 1.0, 1.0, 0.2])
    J -= np.outer(J @ twist, twist)
    answers = []
    for leak in (1e-6, 1e-3):
        information = J.T @ J + leak * np.outer(twist, twist)
        cov = np.linalg.inv(information)
        answers.append(rotation_std_deg(cov, pose, sym))
        # Read as asymmetric, the same fit is hopelessly uncertain.
        assert rotation_std_deg(cov, pose, NONE) > 10 * answers[-1]
    # The answer does not depend on how little of the turn leaks through.
    assert math.isclose(answers[0], answers[1], rel_tol=1e-3)
    assert answers[0] < 1.0


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-math.pi, math.pi), min_size=3, max_size=3),
       st.lists(st.floats(0.05, 5.0), min_size=6, max_size=6), st.booleans())
def test_it_does_not_depend_on_the_camera_axes(turn, deviations, symmetric):
    # The same uncertainty expressed in camera axes turned by Q (rotation
    # and translation blocks alike) with the pose turned by Q too.
    rng = np.random.default_rng(7)
    A = rng.normal(size=(6, 6)) * 0.1 + np.diag(np.radians(deviations[:3]).tolist()
                                                + deviations[3:])
    cov = A @ A.T
    Q = Rotation.from_rotvec(turn).as_matrix()
    big = np.zeros((6, 6))
    big[:3, :3] = big[3:, 3:] = Q
    pose = _pose(Rotation.from_euler("zyx", [20.0, 30.0, -40.0], degrees=True).as_matrix())
    turned = Pose(Q @ pose.R_m2c, Q @ pose.t_m2c)
    sym = ABOUT_Z if symmetric else NONE
    assert math.isclose(rotation_std_deg(cov, pose, sym),
                        rotation_std_deg(big @ cov @ big.T, turned, sym), rel_tol=1e-6)
