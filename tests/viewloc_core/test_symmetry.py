"""Symmetry detection, BOP declarations, discretisation and the canonical pose."""

import math
import time

import numpy as np
import pytest
import trimesh
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from tests.viewloc_core.conftest import ribbed_bracket
from viewloc_core.errors import InvalidInputError
from viewloc_core.pose import Pose, rotation_angle_deg
from viewloc_core.symmetry import (
    Symmetries,
    any_within_angle_deg,
    canonical_pose,
    declared_symmetries,
    detect_symmetries,
    min_rotation_error_deg,
    symmetries_from_bop,
    symmetries_to_bop,
    symmetry_transforms,
    within_angle_deg,
)


def _box() -> trimesh.Trimesh:
    return trimesh.creation.box((120.0, 60.0, 30.0))


def _cylinder() -> trimesh.Trimesh:
    return trimesh.creation.cylinder(radius=25.0, height=90.0, sections=48)


def _barbell() -> trimesh.Trimesh:
    """A bar along x with a disc plate at each end, about 180 mm long."""
    bar = trimesh.creation.cylinder(radius=6.0, height=180.0, sections=32)
    bar.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, [0, 1, 0]))
    parts = [bar]
    for x in (-70.0, 70.0):
        disc = trimesh.creation.cylinder(radius=35.0, height=12.0, sections=48)
        disc.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, [0, 1, 0]))
        disc.apply_translation([x, 0.0, 0.0])
        parts.append(disc)
    return trimesh.util.concatenate(parts)


def _moved(mesh: trimesh.Trimesh, R: np.ndarray, t: np.ndarray) -> trimesh.Trimesh:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    out = mesh.copy()
    out.apply_transform(T)
    return out


def _is_symmetry(mesh: trimesh.Trimesh, T: np.ndarray, tol: float) -> bool:
    """Every moved sample lies within ``tol`` mm of a dense independent sample."""
    pts, _ = trimesh.sample.sample_surface(mesh, 2000, seed=11)
    dense, _ = trimesh.sample.sample_surface(mesh, 60000, seed=12)
    moved = pts @ T[:3, :3].T + T[:3, 3]
    d, _ = cKDTree(dense).query(moved)
    return bool(d.max() < tol)


def test_box_has_three_two_fold_axes():
    sym = detect_symmetries(_box())
    assert sym.continuous_axis is None
    assert len(sym.discrete) == 4
    angles = sorted(rotation_angle_deg(np.eye(3), T[:3, :3]) for T in sym.discrete)
    assert angles[0] == pytest.approx(0.0, abs=1e-6)
    assert angles[1:] == pytest.approx([180.0] * 3, abs=0.5)
    for T in sym.discrete:
        assert _is_symmetry(_box(), T, 2.0)


def test_cylinder_has_continuous_axis_and_flip():
    sym = detect_symmetries(_cylinder())
    assert sym.continuous_axis is not None
    assert abs(sym.continuous_axis @ [0, 0, 1]) > math.cos(math.radians(1.0))
    assert sym.continuous_offset is not None
    assert np.linalg.norm(np.cross(sym.continuous_offset, sym.continuous_axis)) < 0.5
    assert len(sym.discrete) == 2
    flip = sym.discrete[1]
    assert rotation_angle_deg(np.eye(3), flip[:3, :3]) == pytest.approx(180.0, abs=0.5)
    assert _is_symmetry(_cylinder(), flip, 2.0)


def test_barbell_continuous_about_bar_plus_flip():
    sym = detect_symmetries(_barbell())
    assert sym.continuous_axis is not None
    assert abs(sym.continuous_axis @ [1, 0, 0]) > math.cos(math.radians(1.0))
    assert len(sym.discrete) == 2


def test_l_bracket_has_no_symmetry():
    sym = detect_symmetries(ribbed_bracket())
    assert sym.continuous_axis is None
    assert len(sym.discrete) == 1


def test_cube_gets_all_24_rotations():
    sym = detect_symmetries(trimesh.creation.box((50.0, 50.0, 50.0)))
    assert len(sym.discrete) == 24


def test_off_centre_hole_breaks_the_symmetry():
    """A plate with one small tab on one side: mean distance alone would miss it."""
    plate = trimesh.creation.box((100.0, 60.0, 6.0))
    tab = trimesh.creation.box((12.0, 12.0, 6.0))
    tab.apply_translation([56.0, 20.0, 0.0])
    sym = detect_symmetries(trimesh.util.concatenate([plate, tab]))
    # Only the flip that keeps the tab's corner in place would survive; none does.
    assert len(sym.discrete) == 1 and sym.continuous_axis is None


def _hex_bolt() -> trimesh.Trimesh:
    """A hexagonal head (30 mm across its flats, 13 mm high) on a round
    shank 90 mm long: the head's corners alone show its turn."""
    head = trimesh.creation.cylinder(radius=30.0 / math.sqrt(3.0), height=13.0, sections=6)
    head.apply_translation([0.0, 0.0, -45.0])
    shank = trimesh.creation.cylinder(radius=10.0, height=90.0, sections=64)
    shank.apply_translation([0.0, 0.0, 6.5])
    return trimesh.util.concatenate([head, shank])


def _studded_plate() -> trimesh.Trimesh:
    """A 3 mm plate with three small studs, none where a half turn or a
    mirror of the plate would put another."""
    parts = [trimesh.creation.box((100.0, 60.0, 3.0))]
    for (x, y), r in zip(((-30.0, 15.0), (5.0, -16.0), (32.0, 4.0)), (4.0, 3.0, 2.5),
                         strict=True):
        stud = trimesh.creation.cylinder(radius=r, height=2.0, sections=24)
        stud.apply_translation([x, y, 2.5])
        parts.append(stud)
    return trimesh.util.concatenate(parts)


def test_hex_bolt_is_sixfold_not_continuous():
    """The mean and 99th-percentile tests pass a hex bolt turned by any angle
    (its head is a small share of the surface); its corners do not."""
    bolt = _hex_bolt()
    sym = detect_symmetries(bolt)
    assert sym.continuous_axis is None
    assert len(sym.discrete) == 6
    for T in sym.discrete:
        assert abs(T[:3, :3][:, 2] @ [0.0, 0.0, 1.0]) > math.cos(math.radians(1.0))
        assert _is_symmetry(bolt, T, 2.0)


@pytest.mark.parametrize(("sections", "discrete", "continuous"),
                         [(6, 12, False), (8, 16, False), (24, 2, True), (48, 2, True)])
def test_prisms_keep_their_order_and_fine_polygons_are_cylinders(sections, discrete,
                                                                 continuous):
    """A hexagonal or octagonal prism is n-fold (with its n flips); a 24-gon
    is a tessellated cylinder (24 sections: 1 mm of its 30 mm radius)."""
    sym = detect_symmetries(
        trimesh.creation.cylinder(radius=30.0, height=80.0, sections=sections))
    assert len(sym.discrete) == discrete
    assert (sym.continuous_axis is not None) == continuous


def test_small_studs_break_the_symmetry_of_a_thin_plate():
    """Three studs on a 3 mm plate move few surface samples far when the plate
    is turned over: the farthest hundredth of them shows it."""
    sym = detect_symmetries(_studded_plate())
    assert len(sym.discrete) == 1 and sym.continuous_axis is None


quats = st.tuples(*(st.floats(-1, 1),) * 4).filter(lambda q: np.linalg.norm(q) > 0.1)
shapes = st.sampled_from(["box", "cylinder", "barbell", "l_bracket", "hex_bolt"])
EXPECT = {"box": (4, False), "cylinder": (2, True), "barbell": (2, True), "l_bracket": (1, False),
          "hex_bolt": (6, False)}
MAKERS = {"box": _box, "cylinder": _cylinder, "barbell": _barbell, "l_bracket": ribbed_bracket,
          "hex_bolt": _hex_bolt}


@settings(max_examples=6, deadline=None)
@given(shape=shapes, q=quats, t=st.tuples(*(st.floats(-200, 200),) * 3))
def test_detection_is_invariant_to_a_rigid_motion(shape, q, t):
    R = Rotation.from_quat(np.array(q) / np.linalg.norm(q)).as_matrix()
    mesh = _moved(MAKERS[shape](), R, np.array(t))
    sym = detect_symmetries(mesh)
    n, continuous = EXPECT[shape]
    assert len(sym.discrete) == n
    assert sym.is_continuous == continuous
    for T in sym.discrete[1:]:
        assert _is_symmetry(mesh, T, 2.0)
    if continuous:
        assert sym.continuous_axis is not None and sym.continuous_offset is not None
        C = symmetry_transforms(Symmetries(np.eye(4)[None], sym.continuous_axis,
                                           sym.continuous_offset), continuous_step_deg=37.0)
        assert _is_symmetry(mesh, C[3], 2.0)


def test_bop_round_trip_and_transforms_count():
    sym = detect_symmetries(_cylinder())
    info = symmetries_to_bop(sym)
    assert len(info["symmetries_discrete"]) == 1 and len(info["symmetries_discrete"][0]) == 16
    back = symmetries_from_bop(info)
    np.testing.assert_allclose(back.discrete, sym.discrete)
    assert back.continuous_axis is not None
    Ts = symmetry_transforms(back, continuous_step_deg=10.0)
    assert Ts.shape == (72, 4, 4)
    np.testing.assert_allclose(Ts[0], np.eye(4), atol=1e-12)


def test_bop_declaration_as_in_models_info():
    # LM-O's "can"-like declaration: a 180° flip about z with an offset.
    info = {"symmetries_discrete": [[-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 2.5, 0, 0, 0, 1]]}
    sym = symmetries_from_bop(info)
    assert len(sym.discrete) == 2 and not sym.is_continuous
    np.testing.assert_allclose(sym.discrete[1][:3, 3], [0, 0, 2.5])
    with pytest.raises(InvalidInputError):
        symmetries_from_bop({"symmetries_discrete": [[1, 2, 3]]})
    with pytest.raises(InvalidInputError):
        symmetries_from_bop({"symmetries_continuous": [{"offset": [0, 0, 0]}]})


@settings(max_examples=25, deadline=None)
@given(q=quats, theta=st.floats(-math.pi, math.pi), flip=st.booleans())
def test_canonical_pose_is_the_same_for_all_equivalents(q, theta, flip):
    sym = symmetries_from_bop({
        "symmetries_discrete": [[1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1]],
        "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}],
    })
    R = Rotation.from_quat(np.array(q) / np.linalg.norm(q)).as_matrix()
    pose = Pose(R, np.array([10.0, -20.0, 600.0]))
    S = Rotation.from_rotvec([0, 0, theta]).as_matrix()
    if flip:
        S = S @ np.diag([1.0, -1.0, -1.0])
    other = Pose(R @ S, pose.t_m2c)
    # Poses half-way between two equivalents (a tie) are broken by a fixed
    # rule, but rounding near the tie may go either way: stay clear of it.
    flipped = canonical_pose(Pose(R @ np.diag([1.0, -1.0, -1.0]), pose.t_m2c),
                             Symmetries(np.eye(4)[None], np.array([0.0, 0, 1]), np.zeros(3)))
    plain = canonical_pose(pose, Symmetries(np.eye(4)[None], np.array([0.0, 0, 1]),
                                            np.zeros(3)))
    assume(abs(rotation_angle_deg(np.eye(3), flipped.R_m2c)
               - rotation_angle_deg(np.eye(3), plain.R_m2c)) > 1e-3)
    a, b = canonical_pose(pose, sym), canonical_pose(other, sym)
    assert rotation_angle_deg(a.R_m2c, b.R_m2c) < 1e-5
    np.testing.assert_allclose(a.t_m2c, pose.t_m2c, atol=1e-9)
    # Canonical means closest to the identity among all equivalents.
    Rs = R @ symmetry_transforms(sym, 5.0)[:, :3, :3]
    best_cos = (np.trace(Rs, axis1=1, axis2=2).max() - 1) / 2
    best_deg = np.degrees(np.arccos(min(best_cos, 1.0)))
    assert rotation_angle_deg(np.eye(3), a.R_m2c) <= best_deg + 1e-6
    assert min_rotation_error_deg(R, R @ S, sym) < 1e-5


def _about_z(folds: int, flip: bool, continuous: bool) -> Symmetries:
    """The group of an n-fold axis along z (or a continuous one), with the
    half turn about x that flips it when ``flip``."""
    transforms = [np.eye(4)]
    for k in range(1, folds):
        T = np.eye(4)
        T[:3, :3] = Rotation.from_rotvec([0, 0, 2 * np.pi * k / folds]).as_matrix()
        transforms.append(T)
    if flip:
        transforms += [T @ np.diag([1.0, -1.0, -1.0, 1.0]) for T in list(transforms)]
    return Symmetries(np.stack(transforms), np.array([0.0, 0, 1]) if continuous else None,
                      np.zeros(3) if continuous else None)


@settings(max_examples=60, deadline=None)
@given(a=st.integers(0, 10_000), b=st.integers(0, 10_000), flip=st.booleans(),
       continuous=st.booleans(), folds=st.integers(1, 6))
def test_min_rotation_error_is_the_angle_to_the_nearest_equivalent(a, b, flip, continuous,
                                                                  folds):
    # A part with an n-fold axis (or a continuous one) and optionally a
    # flip: the error is the angle to the symmetric equivalent of the
    # truth closest to the estimate, which canonical_pose picks, and no
    # sampled equivalent is closer.
    sym = _about_z(folds, flip, continuous)
    R_est = Rotation.random(random_state=a).as_matrix()
    R_gt = Rotation.random(random_state=b).as_matrix()
    nearest = canonical_pose(Pose(R_gt, np.array([0.0, 0, 500.0])), sym, R_ref=R_est)
    error = min_rotation_error_deg(R_est, R_gt, sym)
    assert error == pytest.approx(rotation_angle_deg(R_est, nearest.R_m2c), abs=1e-6)
    sampled = R_gt @ symmetry_transforms(sym, 5.0)[:, :3, :3]
    assert error <= min(rotation_angle_deg(R_est, R) for R in sampled) + 1e-6
    # The fast threshold test agrees, away from the threshold.
    for limit in (10.0, 30.0, 90.0, 150.0):
        if abs(error - limit) > 1e-4:
            assert within_angle_deg(R_est, R_gt, sym, limit) == (error < limit)


def test_canonical_pose_discrete_moves_translation_with_offset():
    T = np.eye(4)
    T[:3, :3] = np.diag([-1.0, -1.0, 1.0])
    T[:3, 3] = [20.0, 0.0, 0.0]  # 180° about the z-parallel line through x = 10
    sym = Symmetries(np.stack([np.eye(4), T]))
    pose = Pose(np.diag([-1.0, -1.0, 1.0]), np.array([0.0, 0.0, 500.0]))
    can = canonical_pose(pose, sym)
    assert rotation_angle_deg(np.eye(3), can.R_m2c) < 1e-9
    # The object point at x = 10 (on the axis) stays where it was.
    np.testing.assert_allclose(can.transform(np.array([[10.0, 0, 0]])),
                               pose.transform(np.array([[10.0, 0, 0]])), atol=1e-9)


def test_min_rotation_error_without_symmetry_is_plain_angle():
    R1 = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_matrix()
    R2 = Rotation.from_euler("xyz", [12, 18, 33], degrees=True).as_matrix()
    assert min_rotation_error_deg(R1, R2, Symmetries.none()) == pytest.approx(
        rotation_angle_deg(R1, R2))


def test_canonical_pose_is_the_same_from_every_equivalent():
    """The pose reported for a symmetric part is the canonical one:
    applying any symmetry to it and canonicalising again gives it back."""
    from viewloc_core.pose import Pose
    from viewloc_core.symmetry import Symmetries, canonical_pose

    sym = Symmetries(np.stack([np.eye(4), np.diag([1.0, -1.0, -1.0, 1.0])]),
                     np.array([1.0, 0.0, 0.0]), np.zeros(3))
    rng = np.random.default_rng(4)
    for _ in range(5):
        R = Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix()
        pose = canonical_pose(Pose(R, np.array([1.0, 2.0, 500.0])), sym)
        spun = Rotation.from_rotvec([rng.uniform(0, 2 * np.pi), 0, 0]).as_matrix()
        other = Pose(pose.R_m2c @ spun @ np.diag([1.0, -1.0, -1.0]), pose.t_m2c)
        again = canonical_pose(other, sym)
        np.testing.assert_allclose(again.R_m2c, pose.R_m2c, atol=1e-6)


# -- symmetries declared by the user (spec.symmetries of POST /v1/objects) -----------------
_FLIP_X = [1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1]
_TURN_Z_90 = [0, -1, 0, 0, 1, 0, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]


def _flat(R: np.ndarray, t: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> list[float]:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return [float(v) for v in T.reshape(16)]


@pytest.mark.parametrize(("info", "field"), [
    ({"symmetries_discrete": [_FLIP_X, [1, 2, 3]]}, "symmetries_discrete[1]"),
    ({"symmetries_discrete": [[*_FLIP_X[:15], float("nan")]]}, "symmetries_discrete[0]"),
    ({"symmetries_discrete": [[2, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]]},
     "symmetries_discrete[0]"),
    # A mirror image is orthonormal but no rigid motion.
    ({"symmetries_discrete": [_FLIP_X, [-1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]]},
     "symmetries_discrete[1]"),
    ({"symmetries_discrete": [[*_FLIP_X[:12], 0, 0, 1, 1]]}, "symmetries_discrete[0]"),
    ({"symmetries_continuous": [{"axis": [0, 0, 1]}, {"axis": [1, 0, 0]}]},
     "symmetries_continuous"),
    ({"symmetries_continuous": [{"axis": [0, 0, 0], "offset": [0, 0, 0]}]},
     "symmetries_continuous[0].axis"),
    ({"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, math.inf, 0]}]},
     "symmetries_continuous[0].offset"),
    ({"symmetries_continuous": [{"offset": [0, 0, 0]}]}, "symmetries_continuous[0].axis"),
    # About x by 1 rad never closes into a finite group.
    ({"symmetries_discrete": [_flat(Rotation.from_rotvec([1.0, 0, 0]).as_matrix())]},
     "symmetries_discrete"),
    # With a continuous axis z, a 90° turn about x moves the axis.
    ({"symmetries_discrete": [[1, 0, 0, 0, 0, 0, -1, 0, 0, 1, 0, 0, 0, 0, 0, 1]],
      "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}]},
     "symmetries_discrete[0]"),
])
def test_declared_symmetries_name_the_bad_entry(info, field):
    with pytest.raises(InvalidInputError) as err:
        declared_symmetries(info)
    assert err.value.field == field


def test_declared_symmetries_must_map_the_part_onto_itself():
    half_turn_z = Rotation.from_rotvec([0, 0, math.pi]).as_matrix()
    # A part reaching 30 mm from its origin: a half turn about the
    # z-parallel line through (10, 0, 0) moves the origin 20 mm.
    sym = declared_symmetries({"symmetries_discrete": [_flat(half_turn_z, (20.0, 0, 0))]},
                              reach_mm=30.0)
    assert len(sym.discrete) == 2
    # Its axis through (31, 0, 0) would move it 62 mm: off the part.
    for t in ((62.0, 0.0, 0.0), (2e300, 0.0, 0.0), (1.7e308, 1.7e308, 0.0)):
        with pytest.raises(InvalidInputError) as err:
            declared_symmetries({"symmetries_discrete": [_flat(half_turn_z, t)]},
                                reach_mm=30.0)
        assert err.value.field == "symmetries_discrete[0]"
    # Any point of the axis may be given: (0, 0, 1 m) on the z axis is the z axis.
    far_on_axis = declared_symmetries(
        {"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 1000.0]}]},
        reach_mm=30.0)
    assert far_on_axis.is_continuous
    for offset, to_mm in (([31.0, 0, 0], 1.0), ([1000.0, 0, 0], 1.0),
                          ([1.7e308, 1.7e308, 0], 1.0), ([1e308, 0, 0], 10.0)):
        with pytest.raises(InvalidInputError) as err:
            declared_symmetries(
                {"symmetries_continuous": [{"axis": [0, 0, 1], "offset": offset}]},
                to_mm=to_mm, reach_mm=30.0)
        assert err.value.field == "symmetries_continuous[0].offset"
    # Without a reach nothing of it is checked (trusted BOP files, old jobs).
    assert declared_symmetries(
        {"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [1000.0, 0, 0]}]}
    ).is_continuous


def test_declared_groups_are_closed_or_refused_without_delay():
    # 240 turns a little off 90° each (0.006° apart) generate no finite
    # group; one by one comparisons took over ten minutes to say so.
    near = [_flat(Rotation.from_rotvec([0, 0, math.pi / 2 + 1e-4 * i]).as_matrix())
            for i in range(240)]
    t0 = time.perf_counter()
    with pytest.raises(InvalidInputError) as err:
        declared_symmetries({"symmetries_discrete": near})
    assert err.value.field == "symmetries_discrete"
    # The largest group allowed, given whole: 240 turns of 1.5° about z.
    cyclic = [_flat(Rotation.from_rotvec([0, 0, math.radians(1.5 * k)]).as_matrix())
              for k in range(240)]
    assert len(declared_symmetries({"symmetries_discrete": cyclic}).discrete) == 240
    # Both within seconds on the 2-core machine (about 0.1 and 1.5 s).
    assert time.perf_counter() - t0 < 30.0


def test_declared_discrete_group_is_closed_and_scaled_to_mm():
    # 90° about the z-parallel line through (1 cm, 0, 0), declared in cm.
    turn = np.array(_TURN_Z_90, float).reshape(4, 4)[:3, :3]
    # The identity, declared or not, is not repeated.
    sym = declared_symmetries({"symmetries_discrete": [_flat(turn, (1.0, -1.0, 0.0)),
                                                       _flat(np.eye(3))]}, to_mm=10.0)
    assert len(sym.discrete) == 4 and not sym.is_continuous
    np.testing.assert_allclose(sym.discrete[0], np.eye(4))
    for S in sym.discrete:
        # Every element keeps the axis point (10 mm, 0, 0) in place.
        np.testing.assert_allclose(S[:3, :3] @ [10.0, 0, 0] + S[:3, 3], [10.0, 0, 0],
                                   atol=1e-9)
    angles = sorted(round(rotation_angle_deg(np.eye(3), S[:3, :3])) for S in sym.discrete)
    assert angles == [0, 90, 90, 180]
    assert declared_symmetries({}).discrete.shape == (1, 4, 4)


def test_declared_continuous_axis_keeps_one_flip():
    # A turn about the axis is implied by it; two flips differ only by a turn.
    turn = Rotation.from_rotvec([0, 0, 0.3]).as_matrix()
    sym = declared_symmetries({
        "symmetries_discrete": [_flat(turn), _FLIP_X, _flat(turn @ np.diag([1.0, -1.0, -1.0]))],
        "symmetries_continuous": [{"axis": [0, 0, 2], "offset": [0, 0, 0.5]}],
    }, to_mm=10.0)
    assert sym.is_continuous and len(sym.discrete) == 2
    np.testing.assert_allclose(sym.continuous_axis, [0, 0, 1])
    np.testing.assert_allclose(sym.continuous_offset, [0, 0, 5.0])
    np.testing.assert_allclose(sym.discrete[1], np.array(_FLIP_X, float).reshape(4, 4))


def test_learning_stores_the_declared_group_and_localize_canonicalises_with_it(tmp_path):
    from model_store.files import load_model_dir, save_model_dir
    from viewloc_core.learn import LearningConfig, learn_from_mesh

    # A box is detected with three 2-fold axes; this station declares it
    # asymmetric (a mark QA cares about) in one model, and in the other adds
    # a continuous axis the detector would never accept.
    mesh = trimesh.creation.box((60.0, 30.0, 15.0))
    config = LearningConfig(max_level=0, min_level=0, contour_level=1, object_px=64)
    plain = learn_from_mesh(mesh, config, symmetries=declared_symmetries({}))
    assert plain.symmetries.shape == (1, 4, 4) and plain.symmetry_axis is None
    declared = declared_symmetries({"symmetries_discrete": [_FLIP_X],
                                    "symmetries_continuous": [{"axis": [1, 0, 0],
                                                               "offset": [0, 0, 0]}]})
    model = learn_from_mesh(mesh, config, symmetries=declared)
    save_model_dir(tmp_path / "m", model)
    back = load_model_dir(tmp_path / "m")
    np.testing.assert_allclose(back.symmetries, declared.discrete)
    assert back.symmetry_axis is not None
    np.testing.assert_allclose(back.symmetry_axis, [1, 0, 0, 0, 0, 0])
    group = back.symmetry_group()
    R = Rotation.from_euler("xyz", [30, -20, 50], degrees=True).as_matrix()
    pose = Pose(R, np.array([5.0, -3.0, 400.0]))
    spun = Rotation.from_rotvec([1.234, 0, 0]).as_matrix() @ np.diag([1.0, -1.0, -1.0])
    a = canonical_pose(pose, group)
    b = canonical_pose(Pose(R @ spun, pose.t_m2c), group)
    assert rotation_angle_deg(a.R_m2c, b.R_m2c) < 1e-6
    # The asymmetric declaration keeps the poses apart (the detector's group would not).
    flipped = Pose(R @ np.diag([1.0, -1.0, -1.0]), pose.t_m2c)
    none = plain.symmetry_group()
    assert rotation_angle_deg(canonical_pose(flipped, none).R_m2c,
                              canonical_pose(pose, none).R_m2c) > 170
    assert rotation_angle_deg(canonical_pose(flipped, detect_symmetries(mesh)).R_m2c,
                              canonical_pose(pose, detect_symmetries(mesh)).R_m2c) < 1e-6


@settings(max_examples=100, deadline=None)
@given(a=st.integers(0, 10_000), n_tried=st.integers(0, 4), flip=st.booleans(),
       continuous=st.booleans(), folds=st.integers(1, 4), turn_deg=st.floats(0.0, 360.0),
       off_deg=st.floats(0.0, 40.0), limit=st.sampled_from([3.0, 10.0, 30.0]))
def test_the_batch_test_holds_when_one_of_its_rotations_is_within_the_angle(
        a, n_tried, flip, continuous, folds, turn_deg, off_deg, limit):
    sym = _about_z(folds, flip, continuous)
    rotations = Rotation.random(n_tried + 1, random_state=a).as_matrix()
    R_a, tried = rotations[0], list(rotations[1:])
    # And one that is R_a turned about the symmetry axis (an equivalent of
    # it only when the turn is in the group), perhaps flipped, then tilted
    # off_deg: both answers occur, and only a test that reads the
    # symmetries gets them right.
    flipped = np.diag([1.0, -1.0, -1.0]) if flip and a % 2 else np.eye(3)
    tried.append(R_a @ Rotation.from_rotvec([0.0, 0.0, math.radians(turn_deg)]).as_matrix()
                 @ flipped @ Rotation.from_rotvec([math.radians(off_deg), 0.0, 0.0]).as_matrix())
    errors = [min_rotation_error_deg(R_a, R, sym) for R in tried]
    assume(all(abs(e - limit) > 1e-4 for e in errors))
    expected = any(within_angle_deg(R_a, R, sym, limit) for R in tried)
    assert any_within_angle_deg(R_a, tried, sym, limit) == expected
    assert expected == any(e < limit for e in errors)
    assert not any_within_angle_deg(R_a, [], sym, limit)
