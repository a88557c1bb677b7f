"""Metrics against hand-computed cases."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from viewloc_core import metrics as m
from viewloc_core.camera import Camera
from viewloc_core.errors import InvalidInputError
from viewloc_core.pose import Pose, rot_z

CUBE = np.array([[x, y, z] for x in (-10.0, 10.0) for y in (-10.0, 10.0) for z in (-10.0, 10.0)])


def rot(axis: str, deg: float) -> np.ndarray:
    return Rotation.from_euler(axis, deg, degrees=True).as_matrix()


def test_g_paper_example_from_the_text() -> None:
    gt = Pose(np.eye(3), np.array([0.0, 0.0, 800.0]))
    # 23 mm across the line of sight (split over x and y), 230 mm along it, 15°.
    est = Pose(rot("y", 15.0), np.array([23.0 * 0.6, 23.0 * 0.8, 800.0 + 230.0]))
    dz, dxy, da = m.paper_deltas(est, gt)
    assert dz == pytest.approx(230.0)
    assert dxy == pytest.approx(23.0)
    assert da == pytest.approx(15.0)
    expected = 1.0 - (230.0**2 / 250000 + 23.0**2 / 50000 + 15.0**2 / 10000)
    assert expected == pytest.approx(0.75532, abs=1e-5)
    assert m.g_paper(est, gt) == pytest.approx(expected)


def test_g_is_one_for_a_perfect_pose_and_clipped_at_zero() -> None:
    gt = Pose(rot("x", 40.0), np.array([10.0, -5.0, 700.0]))
    assert m.g_paper(gt, gt) == pytest.approx(1.0)
    far = Pose(gt.R_m2c, gt.t_m2c + np.array([0.0, 0.0, 600.0]))
    assert m.g_paper(far, gt) == 0.0


def test_g_minimises_the_angle_over_symmetries() -> None:
    gt = Pose(np.eye(3), np.array([0.0, 0.0, 600.0]))
    est = Pose(rot("z", 178.0), gt.t_m2c)
    assert m.paper_deltas(est, gt)[2] == pytest.approx(178.0)
    flip = np.eye(4)
    flip[:3, :3] = rot("z", 180.0)
    syms = m.symmetry_transforms(discrete=[flip])
    assert syms.shape == (2, 4, 4)
    assert m.paper_deltas(est, gt, syms)[2] == pytest.approx(2.0)
    assert m.g_paper(est, gt, syms) == pytest.approx(1.0 - 4.0 / 10000)


def test_continuous_symmetry_discretisation() -> None:
    syms = m.symmetry_transforms(continuous=[(np.array([1.0, 0, 0]), np.zeros(3))], step_deg=1.0)
    assert syms.shape == (360, 4, 4)
    assert np.allclose(syms[0], np.eye(4))
    for S in syms[::37]:
        assert np.allclose(S[:3, :3] @ S[:3, :3].T, np.eye(3))
        assert np.allclose(S[:3, :3] @ [1.0, 0, 0], [1.0, 0, 0])
    # Axis through an offset point: that point stays put.
    off = np.array([0.0, 5.0, 0.0])
    syms_off = m.symmetry_transforms(continuous=[(np.array([0, 0, 1.0]), off)], step_deg=90.0)
    assert len(syms_off) == 4
    for S in syms_off:
        assert np.allclose(S[:3, :3] @ off + S[:3, 3], off)
    gt = Pose(np.eye(3), np.array([0.0, 0.0, 500.0]))
    est = Pose(rot("x", 33.3), gt.t_m2c)
    assert m.paper_deltas(est, gt, syms)[2] == pytest.approx(0.3, abs=1e-6)


def test_mssd_mspd_translated_cube() -> None:
    cam = Camera(500.0, 500.0, 320.0, 240.0, 640, 480)
    gt = Pose(np.eye(3), np.array([0.0, 0.0, 1000.0]))
    est = Pose(np.eye(3), np.array([3.0, 4.0, 1000.0]))
    assert m.mssd(est, gt, CUBE) == pytest.approx(5.0)
    # Pure sideways shift: every vertex moves by 5 * f / z_i px, largest at z = 990.
    assert m.mspd(est, gt, CUBE, cam) == pytest.approx(5.0 * 500.0 / 990.0)
    # ADD-S of a pure translation of a cube whose vertices are 20 mm apart: 5 mm.
    assert m.add_s(est, gt, CUBE) == pytest.approx(5.0)


def test_mssd_rotated_cube_and_its_symmetry() -> None:
    gt = Pose(np.eye(3), np.array([0.0, 0.0, 800.0]))
    est = Pose(rot("z", 90.0), gt.t_m2c)
    # A vertex (10, 10, z) goes to (-10, 10, z): 20 mm; all vertices move 20 mm.
    assert m.mssd(est, gt, CUBE) == pytest.approx(20.0)
    quarter = np.eye(4)
    quarter[:3, :3] = rot("z", 90.0)
    syms = np.stack([np.eye(4), quarter])
    assert m.mssd(est, gt, CUBE, syms) == pytest.approx(0.0, abs=1e-9)
    cam = Camera(600.0, 600.0, 320.0, 240.0, 640, 480)
    assert m.mspd(est, gt, CUBE, cam, syms) == pytest.approx(0.0, abs=1e-9)
    # ADD-S is blind to the cube's own symmetries.
    assert m.add_s(est, gt, CUBE) == pytest.approx(0.0, abs=1e-9)
    # Rotation about the centre by 180° around x: |(0, 2y, 2z)| = 20*sqrt(2).
    est_x = Pose(rot("x", 180.0), gt.t_m2c)
    assert m.mssd(est_x, gt, CUBE) == pytest.approx(20.0 * np.sqrt(2.0))


def test_symmetry_with_translation_part() -> None:
    # A symmetry S that maps the model onto itself with a shift of the origin.
    S = np.eye(4)
    S[:3, :3] = rot_z(np.pi)
    S[:3, 3] = [20.0, 0.0, 0.0]  # rotate about the line x = 10
    pts = np.array([[0.0, 0, 0], [20.0, 0, 0], [10.0, 5.0, 0.0], [10.0, -5.0, 0.0]])
    gt = Pose(np.eye(3), np.array([0.0, 0.0, 500.0]))
    moved = Pose(gt.R_m2c @ S[:3, :3], gt.R_m2c @ S[:3, 3] + gt.t_m2c)
    syms = np.stack([np.eye(4), S])
    assert m.mssd(moved, gt, pts, syms) == pytest.approx(0.0, abs=1e-9)
    assert m.g_paper(moved, gt, syms) == pytest.approx(1.0)
    assert m.mssd(moved, gt, pts) > 10.0


def test_thresholds_and_recall() -> None:
    assert np.allclose(m.mssd_thresholds_mm(200.0), np.arange(1, 11) * 10.0)
    assert np.allclose(m.mspd_thresholds_px(640), np.arange(1, 11) * 5.0)
    assert np.allclose(m.mspd_thresholds_px(384), np.arange(1, 11) * 3.0)
    errors = np.array([4.0, 5.0, 12.0, np.inf, np.nan])
    rec = m.recall_at(errors, np.array([5.0, 10.0, 15.0]))
    # Strictly below the threshold, as in BOP; inf and nan (no detection) miss.
    assert np.allclose(rec, [1 / 5, 2 / 5, 3 / 5])
    assert m.average_recall(errors, np.array([5.0, 10.0, 15.0])) == pytest.approx(0.4)
    per_target = np.array([[5.0, 10.0], [1.0, 2.0]])
    assert np.allclose(m.recall_at(np.array([4.0, 4.0]), per_target), [0.5, 0.5])
    assert np.allclose(m.recall_at(np.array([]), np.array([1.0, 2.0])), [0.0, 0.0])


def test_recognized_definitions() -> None:
    cam = Camera(500.0, 500.0, 200.0, 150.0, 400, 300)
    gt = Pose(np.eye(3), np.array([0.0, 0.0, 1000.0]))
    # 180 mm at 1 m with f = 500 px: 90 px image diameter, so 9 px tolerance.
    assert m.image_diameter_px(cam, gt, 180.0) == pytest.approx(90.0)
    assert m.recognized_2d(np.array([208.9, 150.0]), cam, gt, 180.0)
    assert not m.recognized_2d(np.array([209.1, 150.0]), cam, gt, 180.0)
    assert not m.recognized_2d(None, cam, gt, 180.0)
    assert m.recognized_6d(17.9, 180.0)
    assert not m.recognized_6d(18.0, 180.0)
    assert not m.recognized_6d(None, 180.0)


def test_bad_input_raises() -> None:
    gt = Pose.identity()
    with pytest.raises(InvalidInputError):
        m.mssd(gt, gt, np.zeros((3, 2)))
    with pytest.raises(InvalidInputError):
        m.g_paper(gt, gt, np.zeros((2, 3, 3)))
