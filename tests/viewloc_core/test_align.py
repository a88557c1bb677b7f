"""Probabilistic alignment: recover known similarities, find views in clutter."""

from dataclasses import replace

import cv2
import numpy as np
import pytest

from tests.viewloc_core.conftest import render_scene
from viewloc_core import similarity as sim2
from viewloc_core.align import align, refine_at_model_scale
from viewloc_core.camera import Camera
from viewloc_core.features import extract_features
from viewloc_core.localize import model_index
from viewloc_core.pose import Pose


def _training_image(renderer, mesh, model, t):
    size = model.train_size_px
    c = (size - 1) / 2.0
    cam = Camera(model.f_train_px, model.f_train_px, c, c, size, size)
    R = model.training.R_m2c[t]
    pose = Pose(R, np.array([0.0, 0.0, model.d0_mm]) - R @ model.origin_offset_mm)
    return renderer.render(mesh, cam, pose, background_rgb=(20, 20, 20)).color, c


@pytest.mark.parametrize(
    ("angle_deg", "scale", "shift"),
    [(25.0, 1.2, (40.0, -20.0)), (-120.0, 0.8, (-15.0, 30.0)), (170.0, 1.5, (60.0, 45.0))],
)
def test_recovers_similarity_of_a_warped_training_image(
    renderer, bracket_mesh, bracket_model, angle_deg, scale, shift
):
    model = bracket_model
    # A training view that founded its model view (its similarity is the identity).
    t = int(np.flatnonzero(np.all(model.training.sim_to_model == [0, 0, 0, 1], axis=1))[0])
    view = int(model.training.model_view[t])
    image, c = _training_image(renderer, bracket_mesh, model, t)
    out_w, out_h = 400, 320
    a = np.radians(angle_deg)
    A = scale * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    centre_out = np.array([out_w / 2 + shift[0], out_h / 2 + shift[1]])
    M = np.hstack([A, (centre_out - A @ np.array([c, c]))[:, None]])
    warped = cv2.warpAffine(image, M, (out_w, out_h), flags=cv2.INTER_LINEAR,
                            borderValue=(20, 20, 20))
    # Search that model view alone: another view of similar appearance may
    # legitimately win on the full model, with its own frame.
    single = replace(model, model_views=[model.model_views[view]])
    matches = align(single, model_index(single), extract_features(warped))
    assert matches, "no match"
    # Expected: model frame (centred) -> training pixels (+c) -> warp.
    expected = np.array([centre_out[0], centre_out[1], a, scale])
    view_data = single.model_views[0]
    got, _, _ = refine_at_model_scale(
        warped, matches[0].sim, view_data.edge_xy.astype(float),
        view_data.edge_theta.astype(float), model_index(single).view_radius_px,
    )
    assert np.hypot(*(got[:2] - expected[:2])) < 1.0
    assert abs(np.degrees(sim2.wrap_angle(got[2] - expected[2]))) < 1.0
    assert abs(got[3] / expected[3] - 1.0) < 0.01


def test_finds_the_object_in_clutter(renderer, bracket_mesh, bracket_model):
    cam = Camera(520.0, 520.0, 201.3, 148.9, 400, 300)
    hits = 0
    rng = np.random.default_rng(7)
    for i in range(4):
        R = cv2.Rodrigues(rng.normal(size=3))[0]
        t = np.array([rng.uniform(-40, 40), rng.uniform(-30, 30), rng.uniform(550, 750)])
        image = render_scene(renderer, bracket_mesh, cam, Pose(R, t), clutter=3, rng=i)
        matches = align(bracket_model, model_index(bracket_model), extract_features(image))
        origin = cam.project((R @ bracket_model.origin_offset_mm + t)[None])[0]
        diameter_px = cam.fx * bracket_model.diameter_mm / t[2]
        if any(np.hypot(*(m.sim[:2] - origin)) < 0.2 * diameter_px for m in matches[:3]):
            hits += 1
    # The object is among the top three candidates; edge-on views of the
    # bracket look like the clutter boxes, so without a distance prior the
    # top-1 ranking in such scenes is not yet reliable (see closing notes).
    assert hits >= 3


def test_blank_image_gives_no_match(bracket_model):
    feats = extract_features(np.full((240, 320, 3), 90, np.uint8))
    assert align(bracket_model, model_index(bracket_model), feats) == []
