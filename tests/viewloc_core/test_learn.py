"""Learning: configuration checks, determinism, both training sources."""

from dataclasses import replace

import cv2
import numpy as np
import pytest
import trimesh

from tests.viewloc_core.conftest import render_scene
from viewloc_core.camera import Camera
from viewloc_core.contour_model import KIND_CREASE, ContourModel, build_contour_model
from viewloc_core.errors import Cancelled, InvalidInputError
from viewloc_core.features import FeatureConfig, extract_features
from viewloc_core.learn import (
    CONTOUR_FACE_RENDERS,
    LearningConfig,
    TrainingView,
    _canonical_camera,
    _canonical_map,
    contour_render_mesh,
    learn_from_images,
    learn_from_mesh,
    outline_hidden_on_black,
)
from viewloc_core.localize import localize
from viewloc_core.mesh import MAX_FACES, mesh_diameter_mm
from viewloc_core.model import model_to_arrays
from viewloc_core.pose import Pose, rotation_angle_deg
from viewloc_core.view_sphere import view_directions


def test_config_from_dict_validates_fields():
    assert LearningConfig.from_dict({"max_level": 1}).max_level == 1
    with pytest.raises(InvalidInputError) as err:
        LearningConfig.from_dict({"max_level": 9})
    assert err.value.field == "learning.max_level"
    with pytest.raises(InvalidInputError) as err:
        LearningConfig.from_dict({"nonsense": 1})
    assert err.value.field == "learning.nonsense"
    with pytest.raises(InvalidInputError):
        LearningConfig.from_dict({"object_px": "big"})
    with pytest.raises(InvalidInputError) as err:
        LearningConfig.from_dict({"contour_level": 5})
    assert err.value.field == "learning.contour_level"
    assert LearningConfig.from_dict({"max_faces": 20_000}).max_faces == 20_000
    assert LearningConfig.from_dict({"visual_hull": False}).visual_hull is False
    for flag in (1, "yes", None):
        with pytest.raises(InvalidInputError) as flag_err:
            LearningConfig.from_dict({"visual_hull": flag})
        assert flag_err.value.field == "learning.visual_hull"
    for faces in (999, MAX_FACES + 1):
        with pytest.raises(InvalidInputError) as err:
            LearningConfig.from_dict({"max_faces": faces})
        assert err.value.field == "learning.max_faces"


@pytest.mark.parametrize(("options", "field"), [
    # Each option in range, together no view: the job failed after upload.
    ({"max_level": 0, "min_level": 0, "max_polar_deg": 30}, "learning.max_polar_deg"),
    ({"contour_level": 0, "max_polar_deg": 30}, "learning.contour_level"),
])
def test_options_that_together_leave_no_view_are_refused(options, field):
    with pytest.raises(InvalidInputError) as err:
        LearningConfig.from_dict(options)
    assert err.value.field == field
    assert "no view" in err.value.message
    # One level finer, a view is left: accepted.
    finer = {k: v + 1 if k.endswith("level") else v for k, v in options.items()}
    config = LearningConfig.from_dict(finer)
    assert view_directions(config.max_level, config.max_polar_deg)
    assert view_directions(config.contour_level, config.max_polar_deg)


def test_a_dense_mesh_is_learned_from_its_simplification(renderer, bracket_mesh, bracket_model):
    # The bracket cut into 9,216 faces (the same shape): learned from 1,000
    # of them, in the uploaded mesh's own frame and size, and still fitted
    # to the millimetre in a render of the dense mesh.
    vertices, faces = bracket_mesh.vertices, bracket_mesh.faces
    for _ in range(4):
        vertices, faces = trimesh.remesh.subdivide(vertices, faces)
    dense = trimesh.Trimesh(vertices, faces, process=False)
    assert len(dense.faces) == 256 * len(bracket_mesh.faces) > 9_000
    stages = []
    model = learn_from_mesh(dense, LearningConfig(max_level=1, min_level=1, max_faces=1_000),
                            progress=lambda stage, fraction: stages.append(stage))
    assert stages[0] == "simplifying the mesh to 1000 faces"
    assert model.mesh_faces is not None and len(model.mesh_faces) <= 1_000
    assert model.diameter_mm == pytest.approx(mesh_diameter_mm(dense), abs=1e-9)
    np.testing.assert_allclose(model.origin_offset_mm, bracket_model.origin_offset_mm, atol=1e-9)
    cam = Camera(560.0, 560.0, 319.5, 239.5, 640, 480)
    pose = Pose(view_directions(1)[9].R_m2c, np.array([30.0, -20.0, 650.0]))
    image = render_scene(renderer, dense, cam, pose)
    dets = localize(model, image, cam).detections
    assert dets
    assert np.linalg.norm(dets[0].pose.t_m2c - pose.t_m2c) < 3.0
    assert rotation_angle_deg(dets[0].pose.R_m2c, pose.R_m2c) < 1.5


def test_a_dense_mesh_s_contour_views_render_its_simplification():
    light = trimesh.creation.icosphere(subdivisions=3)  # 1,280 faces
    assert contour_render_mesh(light, 642) is light
    dense = trimesh.creation.icosphere(subdivisions=6, radius=50.0)  # 81,920 faces
    rendered = contour_render_mesh(dense, 642)
    assert len(rendered.faces) * 642 <= 1.01 * CONTOUR_FACE_RENDERS
    # The same sphere: its vertices stay on the surface.
    assert np.allclose(np.linalg.norm(rendered.vertices, axis=1), 50.0, atol=0.5)


def test_a_simplified_render_finds_the_dense_mesh_s_own_contour(renderer):
    # Visibility from a render of 2,000 faces, points from the 57,344 of the
    # dense box: the same contour as with the dense render, on its surface.
    dense = trimesh.creation.box(extents=(60.0, 40.0, 20.0)).subdivide_to_size(1.0)
    directions = np.array([v.direction for v in view_directions(1)])
    args = (renderer, 240.0, 512.0, (160, 160))
    full = build_contour_model(dense, directions, *args)
    cheap = build_contour_model(dense, directions, *args,
                                visibility_mesh=contour_render_mesh(dense, 5_000))
    assert len(contour_render_mesh(dense, 5_000).faces) <= 2_000 < len(dense.faces)
    assert np.all(np.abs(cheap.counts - full.counts) <= 0.05 * full.counts + 2)
    pts = cheap.points_obj[np.arange(cheap.points_obj.shape[1]) < cheap.counts[:, None]]
    half = np.array([30.0, 20.0, 10.0])
    assert np.all(np.abs(pts) <= half + 1e-3)
    assert np.all(np.isclose(np.abs(pts), half, atol=1e-3).any(axis=1))


def test_model_views_cluster_training_views(bracket_model):
    model = bracket_model
    assert model.training_views == 42
    assert 1 <= model.n_model_views <= model.training_views
    # Every training view belongs to a model view, and founders map by identity.
    assert set(model.training.model_view.tolist()) == set(range(model.n_model_views))
    for view in range(model.n_model_views):
        members = np.flatnonzero(model.training.model_view == view)
        assert model.model_views[view].n_members == len(members)
    # The refinement's contour views come from the finer contour_level
    # sphere (642 directions), not from the 42 training views.
    contour = ContourModel.from_arrays(model.contour)
    assert contour.n_views == len(view_directions(LearningConfig().contour_level)) == 642


def test_learning_is_deterministic(bracket_mesh):
    config = LearningConfig(max_level=0, min_level=0, contour_level=1, seed=3)
    a, meta_a = model_to_arrays(learn_from_mesh(bracket_mesh, config))
    b, meta_b = model_to_arrays(learn_from_mesh(bracket_mesh, config))
    assert meta_a == meta_b
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)


def test_learning_can_be_cancelled(bracket_mesh):
    calls = []

    def stop() -> bool:
        calls.append(1)
        return len(calls) > 3

    with pytest.raises(Cancelled):
        learn_from_mesh(bracket_mesh, LearningConfig(max_level=0, min_level=0, contour_level=1),
                        should_stop=stop)


def test_learning_from_real_style_images(renderer, bracket_mesh):
    # Photos of the part from known viewpoints: here rendered at 640x480
    # with a real-camera-like K, 600 mm away, with an in-plane turn.
    cam = Camera(600.0, 600.0, 319.5, 239.5, 640, 480)
    images, masks, views = [], [], []
    offset = np.asarray(bracket_mesh.bounds).mean(axis=0)
    for v in view_directions(0):
        inplane = 20.0
        R = _inplane(inplane) @ v.R_m2c
        pose = Pose(R, np.array([0.0, 0.0, 600.0]) - R @ offset)
        result = renderer.render(bracket_mesh, cam, pose, background_rgb=(30, 30, 30))
        images.append(result.color)
        masks.append(result.mask)
        views.append(TrainingView(v.azimuth_deg, v.polar_deg, 600.0, inplane))
    config = LearningConfig(max_level=0, min_level=0)
    model = learn_from_images(images, masks, cam, views, 130.0, config)
    assert model.source == "images"
    assert model.training_views == 12
    assert model.n_model_views >= 2
    # Twelve photos are too few to carve a hull: no mesh, no refinement.
    assert model.contour is None and model.mesh_faces is None
    with pytest.raises(InvalidInputError):
        learn_from_images(images, masks[:3], cam, views, 130.0)


@pytest.mark.slow
def test_masked_photos_from_all_round_carve_a_hull_the_poses_are_refined_on(
        renderer, bracket_mesh):
    # 162 masked photos (views about 13° apart), the bracket's bounding-box
    # centre on their optical axes, at 500-700 mm and turned in the plane.
    cam = Camera(520.0, 520.0, 159.5, 119.5, 320, 240)
    offset = np.asarray(bracket_mesh.bounds).mean(axis=0)
    centred = bracket_mesh.copy()
    centred.apply_translation(-offset)
    rng = np.random.default_rng(5)
    images, masks, views = [], [], []
    for v in view_directions(2):
        inplane, distance = float(rng.uniform(-30.0, 30.0)), float(rng.uniform(500.0, 700.0))
        pose = Pose(_inplane(inplane) @ v.R_m2c, np.array([0.0, 0.0, distance]))
        shot = renderer.render(centred, cam, pose, background_rgb=(40, 40, 40))
        images.append(shot.color)
        masks.append(shot.mask)
        views.append(TrainingView(v.azimuth_deg, v.polar_deg, distance, inplane))
    config = LearningConfig()
    model = learn_from_images(images, masks, cam, views, 130.0, config)
    # The hull holds the bracket and is about its size; only its outline
    # is fitted (its creases are where the photos' cones meet).
    assert model.contour is not None and model.mesh_faces is not None
    hull_contour = ContourModel.from_arrays(model.contour)
    assert not np.any(hull_contour.kinds == KIND_CREASE)
    # Its outline from all the contour level's directions (642), as a
    # mesh's.
    assert hull_contour.n_views == 10 * 4 ** config.contour_level + 2
    hull_box = np.array([model.mesh_vertices_mm.min(axis=0), model.mesh_vertices_mm.max(axis=0)])
    bracket_box = np.asarray(centred.bounds)
    assert np.all(hull_box[0] <= bracket_box[0] + 1.0)
    assert np.all(hull_box[1] >= bracket_box[1] - 1.0)
    assert np.all(np.abs(hull_box - bracket_box) < 0.05 * 130.0)
    # Scenes the photos never showed: refined to a degree or two; the
    # hull's outline lies a little inside the photos' masks (its surface is
    # smoothed after carving), which brings the fit a few % nearer.
    scene_cam = Camera(600.0, 600.0, 191.5, 143.5, 384, 288)
    for euler in ([180.0, 55.0, -96.0], [64.0, -158.0, 20.0], [65.0, 133.0, -98.0]):
        truth = Pose.from_euler_xyz_deg(np.array(euler), np.array([15.0, -10.0, 650.0]))
        scene = render_scene(renderer, centred, scene_cam, truth)
        det = localize(model, scene, scene_cam).detections[0]
        assert det.refined
        assert rotation_angle_deg(det.pose.R_m2c, truth.R_m2c) < 3.0
        assert np.all(np.abs(det.pose.t_m2c[:2] - truth.t_m2c[:2]) < 3.0)
        assert abs(det.pose.t_m2c[2] - truth.t_m2c[2]) < 0.04 * truth.t_m2c[2]
    # Without the hull (or without masks) the same photos give no mesh.
    plain = learn_from_images(images, masks, cam, views, 130.0,
                              replace(config, visual_hull=False))
    assert plain.contour is None and plain.mesh_faces is None
    unmasked = learn_from_images(images, None, cam, views, 130.0, config)
    assert unmasked.contour is None and unmasked.mesh_faces is None


def _inplane(angle_deg: float) -> np.ndarray:
    a = np.radians(angle_deg)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])


def test_photos_with_non_square_pixels_and_distortion_warp_like_ideal_ones(renderer, bracket_mesh):
    # The same view through an ideal camera and through a real one with
    # non-square pixels, an offset principal point and barrel distortion
    # must give the same canonical training image.
    ideal = Camera(600.0, 600.0, 319.5, 239.5, 640, 480)
    real = Camera(640.0, 580.0, 326.0, 236.0, 640, 480, dist=(-0.3, 0.1, 0.001, -0.002, 0.0))
    view = view_directions(0)[3]
    R = _inplane(25.0) @ view.R_m2c
    offset = np.asarray(bracket_mesh.bounds).mean(axis=0)
    pose = Pose(R, np.array([0.0, 0.0, 600.0]) - R @ offset)
    photo_ideal = renderer.render(bracket_mesh, ideal, pose, background_rgb=(30, 30, 30)).color
    # Each real pixel sees along the ray its undistorted normalised position gives.
    v, u = np.mgrid[0:480, 0:640].astype(np.float64)
    rays = real.ray(np.column_stack([u.ravel(), v.ravel()]))
    xy_n = rays[:, :2] / rays[:, 2:3]
    to_ideal = xy_n * 600.0 + np.array([319.5, 239.5])
    photo_real = cv2.remap(photo_ideal, to_ideal[:, 0].reshape(480, 640).astype(np.float32),
                           to_ideal[:, 1].reshape(480, 640).astype(np.float32), cv2.INTER_LINEAR)
    training = TrainingView(view.azimuth_deg, view.polar_deg, 600.0, 25.0)
    d0, f, size = _canonical_camera(LearningConfig(), 130.0)

    def canonical(photo: np.ndarray, camera: Camera) -> np.ndarray:
        map_x, map_y = _canonical_map(camera, training, d0, f, size)
        return cv2.remap(photo, map_x, map_y, cv2.INTER_LINEAR).astype(np.float64)

    want = canonical(photo_ideal, ideal)
    got = canonical(photo_real, real)
    lit = want.max(axis=2) > 40
    assert lit.mean() > 0.1
    assert np.abs(got - want)[lit].mean() < 4.0
    # Ignoring the lens would not do: the real photo read as if ideal.
    assert np.abs(canonical(photo_real, ideal) - want)[lit].mean() > 15.0


def _disc(grey: int) -> tuple[np.ndarray, np.ndarray]:
    """A 60 px disc of one grey level over black, and its mask."""
    mask = np.zeros((120, 120), np.uint8)
    cv2.circle(mask, (60, 60), 30, 1, -1)
    image = np.zeros((120, 120, 3), np.uint8)
    image[mask > 0] = grey
    return image, mask > 0


def test_only_a_dark_outline_counts_as_hidden_on_black():
    assert outline_hidden_on_black(*_disc(25))
    assert not outline_hidden_on_black(*_disc(90))
    # A dark rim around a bright part is what the features see over black.
    image, mask = _disc(200)
    rim = mask & ~cv2.erode(mask.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    image[rim] = 20
    assert outline_hidden_on_black(image, mask)
    assert not outline_hidden_on_black(np.zeros((40, 40, 3), np.uint8), np.zeros((40, 40), bool))


def _outline_share(features_xy: np.ndarray, mask: np.ndarray) -> float:
    """Share of the edge samples within 1.5 px of the mask's outline."""
    outline = mask & ~cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    distance = cv2.distanceTransform((~outline).astype(np.uint8), cv2.DIST_L2, 3)
    xy = np.rint(features_xy).astype(int)
    return float((distance[xy[:, 1], xy[:, 0]] <= 1.5).mean())


def test_a_dark_part_is_learned_from_its_outline(bracket_mesh, monkeypatch):
    # A black bracket with a bright rib (as a drill has its chuck) over
    # black: the rib's edges set the scale of the training view's edge map,
    # the faint black outline ranks with the texture inside, and the
    # templates hold as much of the inside as of the outline, although any
    # real background shows the outline best. Over white it stands out.
    dark = bracket_mesh.copy()
    colours = np.tile([25, 25, 28, 255], (len(dark.vertices), 1)).astype(np.uint8)
    colours[-8:, :3] = 230  # the rib, the last of the three boxes
    dark.visual.vertex_colors = colours
    import viewloc_core.learn as learn_module

    seen: list[tuple[np.ndarray, np.ndarray]] = []
    sample = learn_module._sample_from_image

    def capture(image, mask, *args):
        seen.append((image, mask))
        return sample(image, mask, *args)

    def outline_share() -> float:
        return float(np.median([
            _outline_share(extract_features(image, FeatureConfig(), mask=mask).edge_xy, mask)
            for image, mask in seen]))

    monkeypatch.setattr(learn_module, "_sample_from_image", capture)
    model = learn_from_mesh(dark, LearningConfig(max_level=0, min_level=0))
    assert model.colour_histogram is not None
    assert len(seen) == 12
    assert all((image[~mask] == 255).mean() > 0.99 for image, mask in seen)
    over_white = outline_share()
    # The same views over black (measured: 0.73 of the edges on the
    # outline, 0.87 over white).
    seen.clear()
    monkeypatch.setattr(learn_module, "DARK_OUTLINE_LEVEL", 0.0)
    learn_from_mesh(dark, LearningConfig(max_level=0, min_level=0))
    assert over_white > 0.8 > outline_share() + 0.05
    # A part of ordinary brightness keeps black.
    monkeypatch.undo()
    monkeypatch.setattr(learn_module, "_sample_from_image", capture)
    seen.clear()
    learn_from_mesh(bracket_mesh, LearningConfig(max_level=0, min_level=0))
    assert all((image[~mask] == 0).mean() > 0.99 for image, mask in seen)
