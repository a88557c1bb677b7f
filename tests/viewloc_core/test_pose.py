"""Rotation and pose properties (DESIGN.md §3: geometry gets property tests)."""

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from viewloc_core.pose import (
    Pose,
    orthonormalize,
    reorthonormalized,
    rotation_about_axis,
    rotation_angle_deg,
    rotation_between,
)

finite = st.floats(-1.0, 1.0, allow_nan=False)
quats = st.tuples(finite, finite, finite, finite).filter(
    lambda q: np.linalg.norm(q) > 1e-3
)
trans = st.tuples(*(st.floats(-2000, 2000, allow_nan=False),) * 3)


@given(quats, trans)
def test_quaternion_round_trip_is_orthonormal(q, t):
    pose = Pose.from_quaternion(np.array(q), np.array(t))
    R = pose.R_m2c
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
    assert abs(np.linalg.det(R) - 1.0) < 1e-9
    q_back = pose.quaternion_wxyz
    assert q_back[0] >= 0
    assert abs(np.linalg.norm(q_back) - 1.0) < 1e-9
    again = Pose.from_quaternion(q_back, pose.t_m2c)
    assert rotation_angle_deg(R, again.R_m2c) < 1e-6


@given(quats, trans)
def test_euler_round_trip(q, t):
    pose = Pose.from_quaternion(np.array(q), np.array(t))
    again = Pose.from_euler_xyz_deg(pose.euler_xyz_deg, pose.t_m2c)
    np.testing.assert_allclose(again.R_m2c, pose.R_m2c, atol=1e-7)


@given(quats, trans)
def test_inverse_composes_to_identity(q, t):
    pose = Pose.from_quaternion(np.array(q), np.array(t))
    ident = pose.compose(pose.inverse())
    np.testing.assert_allclose(ident.matrix, np.eye(4), atol=1e-7)


@settings(max_examples=200)
@given(st.tuples(finite, finite, finite), st.tuples(finite, finite, finite))
def test_rotation_between_maps_a_onto_b(a, b):
    a, b = np.array(a), np.array(b)
    if np.linalg.norm(a) < 1e-3 or np.linalg.norm(b) < 1e-3:
        return
    R = rotation_between(a, b)
    np.testing.assert_allclose(R @ (a / np.linalg.norm(a)), b / np.linalg.norm(b), atol=1e-9)
    assert abs(np.linalg.det(R) - 1.0) < 1e-9


def test_euler_convention_is_extrinsic_xyz():
    pose = Pose.from_euler_xyz_deg(np.array([90.0, 0.0, 0.0]), np.zeros(3))
    # x-axis rotation by +90 degrees takes +y to +z.
    np.testing.assert_allclose(pose.R_m2c @ [0, 1, 0], [0, 0, 1], atol=1e-12)


def test_orthonormalize_repairs_a_noisy_rotation():
    rng = np.random.default_rng(0)
    R = orthonormalize(np.eye(3) + 1e-3 * rng.standard_normal((3, 3)))
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) > 0


def test_euler_angles_at_gimbal_lock_round_trip_without_warning():
    import warnings

    for middle in (90.0, -90.0):
        pose = Pose.from_euler_xyz_deg(np.array([30.0, middle, 40.0]), np.zeros(3))
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            angles = pose.euler_xyz_deg
        again = Pose.from_euler_xyz_deg(angles, np.zeros(3))
        assert rotation_angle_deg(again.R_m2c, pose.R_m2c) < 1e-6


@settings(max_examples=200)
@given(st.tuples(finite, finite, finite).filter(lambda a: np.linalg.norm(a) > 1e-3),
       st.floats(-7.0, 7.0, allow_nan=False))
def test_rotation_about_axis_is_scipys_rotation_vector(axis, angle):
    k = np.array(axis) / np.linalg.norm(axis)
    np.testing.assert_allclose(rotation_about_axis(k, angle),
                               Rotation.from_rotvec(k * angle).as_matrix(), atol=1e-12)


@settings(max_examples=200)
@given(quats, st.tuples(finite, finite, finite).filter(lambda a: np.linalg.norm(a) > 1e-3),
       st.floats(0.0, math.pi, allow_nan=False))
def test_rotation_angle_is_the_relative_turn_near_0_and_180_too(q, axis, angle):
    R_a = Pose.from_quaternion(np.array(q), np.zeros(3)).R_m2c
    k = np.array(axis) / np.linalg.norm(axis)
    R_b = R_a @ Rotation.from_rotvec(k * angle).as_matrix()
    assert abs(rotation_angle_deg(R_a, R_b) - math.degrees(angle)) < 1e-9
    for tiny in (1e-9, 1e-7):
        turned = R_a @ Rotation.from_rotvec(k * tiny).as_matrix()
        assert abs(rotation_angle_deg(R_a, turned) - math.degrees(tiny)) < 1e-11


@given(quats, quats, st.floats(-1e-9, 1e-9, allow_nan=False))
def test_a_rotation_off_by_rounding_is_repaired_in_place(q1, q2, noise):
    R = (Pose.from_quaternion(np.array(q1), np.zeros(3)).R_m2c
         @ Pose.from_quaternion(np.array(q2), np.zeros(3)).R_m2c)
    off = R + noise * np.arange(9.0).reshape(3, 3)
    fixed = reorthonormalized(off)
    np.testing.assert_allclose(fixed.T @ fixed, np.eye(3), atol=1e-14)
    np.testing.assert_allclose(fixed, orthonormalize(off), atol=1e-14)
