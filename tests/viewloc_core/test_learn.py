"""Learning: configuration checks, determinism, both training sources."""

import numpy as np
import pytest

from viewloc_core.camera import Camera
from viewloc_core.errors import Cancelled, InvalidInputError
from viewloc_core.learn import LearningConfig, TrainingView, learn_from_images, learn_from_mesh
from viewloc_core.model import model_to_arrays
from viewloc_core.pose import Pose
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


def test_model_views_cluster_training_views(bracket_model):
    model = bracket_model
    assert model.training_views == 42
    assert 1 <= model.n_model_views <= model.training_views
    # Every training view belongs to a model view, and founders map by identity.
    assert set(model.training.model_view.tolist()) == set(range(model.n_model_views))
    for view in range(model.n_model_views):
        members = np.flatnonzero(model.training.model_view == view)
        assert model.model_views[view].n_members == len(members)


def test_learning_is_deterministic(bracket_mesh):
    config = LearningConfig(max_level=0, min_level=0, seed=3)
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
        learn_from_mesh(bracket_mesh, LearningConfig(max_level=0, min_level=0), should_stop=stop)


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
    with pytest.raises(InvalidInputError):
        learn_from_images(images, masks[:3], cam, views, 130.0)


def _inplane(angle_deg: float) -> np.ndarray:
    a = np.radians(angle_deg)
    return np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
