"""Probabilistic alignment: recover known similarities, find views in clutter."""

from dataclasses import replace

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.viewloc_core.conftest import faint_noise, render_scene
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


def test_batched_log_probability_keeps_hypotheses_apart(renderer, bracket_mesh, bracket_model):
    """g of several hypotheses scored at once equals each scored alone, and
    the true similarity beats shifted and rotated ones."""
    from viewloc_core.align import log_probability, log_probability_many

    model = bracket_model
    t = int(np.flatnonzero(np.all(model.training.sim_to_model == [0, 0, 0, 1], axis=1))[0])
    view = int(model.training.model_view[t])
    image, c = _training_image(renderer, bracket_mesh, model, t)
    feats = extract_features(image)
    true_sim = np.array([c, c, 0.0, 1.0])
    other = (view + 1) % len(model.model_views)
    views = [model.model_views[v] for v in (view, view, other, view)]
    sims = np.array([true_sim, true_sim + [25.0, -10.0, 0.0, 0.0], true_sim,
                     true_sim + [0.0, 0.0, 0.6, 0.0]])
    g_many, n_many = log_probability_many(views, feats, sims)
    for h, (v, s) in enumerate(zip(views, sims, strict=True)):
        g_one, n_one = log_probability(v, feats, s)
        assert g_many[h] == pytest.approx(g_one, rel=1e-9, abs=1e-9)
        assert n_many[h] == n_one
    assert g_many[0] > g_many[1] and g_many[0] > g_many[3]
    assert n_many[0] > 0
    g_none, n_none = log_probability_many([], feats, np.zeros((0, 4)))
    assert g_none.shape == (0,) and n_none.shape == (0,)


def test_batched_extension_equals_each_hypothesis_alone(renderer, bracket_mesh, bracket_model):
    """The final fit of several hypotheses at once (padded edge sets of
    different lengths) gives what each gives alone, and snaps a start a few
    pixels and degrees off back onto the training image."""
    from viewloc_core.align import AlignConfig, extend, extend_many

    model = bracket_model
    t = int(np.flatnonzero(np.all(model.training.sim_to_model == [0, 0, 0, 1], axis=1))[0])
    view = int(model.training.model_view[t])
    image, c = _training_image(renderer, bracket_mesh, model, t)
    feats = extract_features(image)
    config = AlignConfig()
    index = model_index(model)
    views = [view, (view + 1) % len(model.model_views), view]
    starts = np.array([[c + 3.0, c - 2.0, 0.05, 1.03], [c, c, 0.0, 1.0],
                       [c - 2.0, c + 1.0, -0.04, 0.98]])
    pts, theta, _, valid = index.fine_samples(np.array(views))
    batched = extend_many(feats, starts, pts, theta, valid, config.icp_radii_px,
                          config.orientation_tol_deg, robust=True)
    for h, v in enumerate(views):
        mv = model.model_views[v]
        alone = extend(feats, starts[h], mv.edge_xy.astype(np.float64),
                       mv.edge_theta.astype(np.float64), config)
        np.testing.assert_allclose(batched[h], alone, rtol=1e-9, atol=1e-9)
    for h in (0, 2):
        assert np.hypot(*(batched[h, :2] - c)) < 0.5
        assert abs(batched[h, 2]) < np.radians(0.5) and abs(batched[h, 3] - 1.0) < 0.005


def test_extension_keeps_the_start_when_the_edges_lie_on_one_line():
    """One straight edge cannot fix a similarity (slide along it, scale):
    the fit is degenerate and the start is kept, not replaced by noise."""
    from viewloc_core.align import AlignConfig, extend

    image = np.full((200, 300), 40, np.uint8)
    image[100:, :] = 200
    feats = extract_features(image)
    pts = np.stack([np.linspace(-60.0, 60.0, 40), np.zeros(40)], axis=1)
    start = np.array([150.0, 101.5, 0.0, 1.0])
    got = extend(feats, start, pts, np.zeros(40), AlignConfig())
    np.testing.assert_array_equal(got, start)


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


def test_suppressed_views_at_a_location_become_alternatives():
    from viewloc_core.align import Match2D, suppress_duplicates

    def m(view, x, g, angle=0.0):
        return Match2D(view, np.array([x, 50.0, angle, 1.0]), g, 0.8, 10)

    out = suppress_duplicates(
        [m(0, 100, 9), m(1, 103, 8), m(0, 101, 7), m(2, 200, 6), m(3, 98, 5), m(4, 99, 4)],
        view_radius_px=40.0, max_matches=5, max_alternatives=2)
    assert [o.model_view for o in out] == [0, 2]
    # Other views only, at most two, in the order given.
    assert [a.model_view for a in out[0].alternatives] == [1, 3]
    assert out[1].alternatives == ()
    # The same view turned far enough is another hypothesis; turned a little, not.
    out = suppress_duplicates([m(0, 100, 9), m(0, 101, 8, 0.3), m(0, 99, 7, np.pi)],
                              view_radius_px=40.0, max_matches=5, max_alternatives=2)
    assert [a.sim[2] for a in out[0].alternatives] == [np.pi]


def _suppress_in_order(matches, view_radius_px, max_matches, max_alternatives):
    """Reference: the plain sequential non-maximum suppression."""
    kept, alternatives = [], []
    for m in matches:
        radius = 0.5 * view_radius_px * m.sim[3]
        near = [i for i, o in enumerate(kept) if np.hypot(*(m.sim[:2] - o.sim[:2])) <= radius]
        if not near:
            if len(kept) < max_matches:
                kept.append(m)
                alternatives.append([])
            continue
        group = [kept[near[0]], *alternatives[near[0]]]
        distinct = all(m.model_view != o.model_view
                       or abs(sim2.wrap_angle(m.sim[2] - o.sim[2])) > np.radians(30.0)
                       for o in group)
        if len(alternatives[near[0]]) < max_alternatives and distinct:
            alternatives[near[0]].append(m)
    return [(k, a) for k, a in zip(kept, alternatives, strict=True)]


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(1, 60), st.integers(1, 6), st.integers(0, 3))
def test_suppression_equals_the_sequential_loop(seed, n, max_matches, max_alternatives):
    """Kept matches and their alternatives are those of a plain loop over the
    matches in order, whatever their scales and however they crowd."""
    from viewloc_core.align import Match2D, suppress_duplicates

    rng = np.random.default_rng(seed)
    sims = np.column_stack([rng.uniform(0, 120, (n, 2)), rng.uniform(-3, 3, n),
                            rng.uniform(0.5, 2.0, n)])
    matches = [Match2D(int(v), s, 0.0, 0.5, 0) for v, s in zip(rng.integers(0, 4, n), sims,
                                                                strict=True)]
    got = suppress_duplicates(matches, 40.0, max_matches, max_alternatives)
    expected = _suppress_in_order(matches, 40.0, max_matches, max_alternatives)
    assert [m.sim.tolist() for m in got] == [k.sim.tolist() for k, _ in expected]
    assert [[a.sim.tolist() for a in m.alternatives] for m in got] == [
        [a.sim.tolist() for a in alts] for _, alts in expected]


def test_outline_evidence_favours_the_true_similarity(renderer, bracket_mesh, bracket_model):
    """The evidence of a model view at its true similarity beats the same view
    shifted, turned or rescaled; a screen on the first samples is the same
    sum over fewer samples; and a view half outside the image is not
    credited for the samples it cannot see."""
    from viewloc_core.align import outline_evidence
    from viewloc_core.edge_evidence import (
        OUTLINE_SCALE_EXPONENT,
        chance_rates,
        lay_over_templates,
    )

    model = bracket_model
    t = int(np.flatnonzero(np.all(model.training.sim_to_model == [0, 0, 0, 1], axis=1))[0])
    view = int(model.training.model_view[t])
    image, c = _training_image(renderer, bracket_mesh, model, t)
    feats = extract_features(image)
    index = model_index(model)
    chance = chance_rates(feats)
    true_sim = np.array([c, c, 0.0, 1.0])
    sims = np.array([true_sim, true_sim + [12.0, -9.0, 0.0, 0.0], true_sim + [0.0, 0.0, 0.5, 0.0],
                     true_sim * [1, 1, 1, 1.3]])
    views = np.full(4, view)
    evidence = outline_evidence(index, feats, views, sims, chance)
    assert evidence[0] > 0 and np.all(evidence[0] > evidence[1:])
    # The screen: the same per-sample evidence on the first 12 samples,
    # times the outline's length, which grows more slowly than the scale.
    few = outline_evidence(index, feats, views, sims, chance, 12)
    llr, _, n_valid, _ = lay_over_templates(
        feats, index.coarse_px[:, :12].copy(), index.coarse_py[:, :12].copy(),
        index.coarse_bins8[:, :12].copy(), index.coarse_valid[:, :12].copy(), views, sims, chance)
    np.testing.assert_allclose(
        few, llr / n_valid * index.outline_px[view] * sims[:, 3] ** OUTLINE_SCALE_EXPONENT)
    assert 0.0 < OUTLINE_SCALE_EXPONENT < 1.0
    # With the image cut through the object, the view loses the evidence of
    # the half it cannot see, but its samples there cost nothing either.
    cut = int(c)
    half = extract_features(np.ascontiguousarray(image[:, cut:]))
    at_edge = np.array([[c - cut, c, 0.0, 1.0]])
    assert 0 < outline_evidence(index, half, views[:1], at_edge, chance)[0] < evidence[0]




def test_crossing_evidence_spares_the_part_and_vanishes_on_plain_ground(
        renderer, bracket_mesh, bracket_model):
    """The part laid over a checkerboard ends the board's lines: at its true
    similarity the crossing term does not count against it, though the
    board's edges are often crossed; on the plain training background the
    term is zero."""
    from viewloc_core.align import outline_crossing_evidence
    from viewloc_core.line_crossing import chance_crossed_rate

    model = bracket_model
    t = int(np.flatnonzero(np.all(model.training.sim_to_model == [0, 0, 0, 1], axis=1))[0])
    view = int(model.training.model_view[t])
    image, c = _training_image(renderer, bracket_mesh, model, t)
    index = model_index(model)
    true_sim = np.array([[c, c, 0.0, 1.0]])
    views = np.array([view])
    plain = extract_features(image)
    assert outline_crossing_evidence(index, plain, views, true_sim,
                                     chance_crossed_rate(plain))[0] == 0.0
    rows, cols = np.indices(image.shape[:2])
    board = np.where((((rows // 16) + (cols // 16)) % 2 == 0)[..., None], 60, 200)
    background = np.all(image == 20, axis=2)[..., None]
    on_board = extract_features(np.where(background, board, image).astype(np.uint8))
    rate = chance_crossed_rate(on_board)
    assert rate > 0.05
    assert outline_crossing_evidence(index, on_board, views, true_sim, rate)[0] >= 0.0


def test_features_of_a_contrasted_part_gain_their_pairing_strength_on_faint_texture():
    """The contrast prior of the pairings: on faint texture the corners of a
    contrasted square gain, the texture's features lose; on a plain
    background every feature is strong and the prior is about 0."""
    from viewloc_core.align import _log_contrast
    from viewloc_core.features import KIND_JUNCTION

    img = faint_noise((300, 400), 6, 1.5, 120, 6)
    cv2.rectangle(img, (150, 100), (260, 190), 210, thickness=-1)
    feats = extract_features(img)
    contrast = _log_contrast(feats)
    g = feats.grouped
    corners = np.array([[150, 100], [260, 100], [260, 190], [150, 190]], float)
    at_corner = (g.kind == KIND_JUNCTION) & (
        np.min(np.linalg.norm(g.xy[:, None, :] - corners[None], axis=2), axis=1) < 3.0)
    far = np.min(np.linalg.norm(g.xy[:, None, :] - corners[None], axis=2), axis=1) > 60.0
    assert at_corner.sum() >= 4 and far.sum() >= 10
    assert np.all(contrast[at_corner] > 0.1)
    assert np.median(contrast[far]) < 0
    plain = np.full((300, 400), 120, np.uint8)
    cv2.rectangle(plain, (150, 100), (260, 190), 210, thickness=-1)
    np.testing.assert_allclose(_log_contrast(extract_features(plain)), 0.0, atol=1e-2)
