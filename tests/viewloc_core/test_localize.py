"""Localization: what a detection reports about where the object is."""

import math
import time
from dataclasses import replace

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from tests.viewloc_core.conftest import (
    ORANGE,
    TABLE_LIGHTS,
    blob,
    coloured_bracket,
    render_copies,
    render_scene,
)
from tests.viewloc_core.test_shading import LIGHTS
from viewloc_core import localize as localize_module
from viewloc_core.align import Match2D
from viewloc_core.camera import Camera
from viewloc_core.detection import Detection, Similarity2D
from viewloc_core.errors import InvalidInputError
from viewloc_core.features import extract_features
from viewloc_core.learn import LearningConfig, learn_from_mesh
from viewloc_core.localize import (
    COLOUR_LEAK_FLOOR,
    COLOUR_LEAK_MAX,
    COLOUR_LEAK_MIN_RARITY,
    COLOUR_LEAK_WEIGHT,
    COLOUR_WEIGHT,
    EVIDENCE_WEIGHT,
    FIGURE_GROUND_FULL,
    FIGURE_GROUND_WEIGHT,
    FINAL_REFINE,
    FINER_SEARCH_NEEDLESS_FRACTION,
    FIRST_FIT_MIN_FIGURE_GROUND,
    GOOD_FIT_FRACTION,
    MIN_COLOUR_AGREEMENT,
    MIN_COLOUR_RANK,
    QUICK_REFINE,
    SHADING_WEIGHT,
    SPARE_MIN_CHANCE_CORRECTED,
    SPARE_MIN_CHANCE_CORRECTED_IN_COLOUR,
    SPARE_MIN_VIEW_EVIDENCE_SHARE,
    TILT_MIN_GAIN,
    LocalizeOptions,
    _after_the_first_convincing,
    _answer_rank,
    _ColourScene,
    _contour_model,
    _convincing,
    _final_detection,
    _finer_search_expected_s,
    _FitOptions,
    _Fitted,
    _Interior,
    _LevelAnswer,
    _Located,
    _LocationFit,
    _non_increasing,
    _on_levels,
    _other_sides,
    _pose_centred,
    _ranked,
    _refine_levels,
    _resolved,
    _settled,
    _Shading,
    _spare_bar_share,
    _spare_locations,
    _supported,
    _surface,
    _tilted_refit,
    _view_candidate_count,
    _visible_first,
    _wider_look,
    localize,
    localize_in_scene,
    prepare_scene,
)
from viewloc_core.near_symmetry import NearSymmetries
from viewloc_core.pose import Pose, rotation_angle_deg
from viewloc_core.refine import RefinementResult, RefineOptions, prepare_edges, refine_pose
from viewloc_core.render import prepare
from viewloc_core.shading import surface_samples
from viewloc_core.symmetry import Symmetries
from viewloc_core.view_search import ViewCandidate
from viewloc_core.view_sphere import view_directions


@pytest.mark.parametrize("refine", [True, False])
def test_reference_point_is_the_image_of_the_mesh_origin(
    renderer, bracket_mesh, bracket_model, refine
):
    # The bracket's mesh origin is far from its bounding-box centre, which
    # the model views are centred on: the reported (x, y) must still be
    # where the mesh origin appears, as the README defines it.
    assert np.linalg.norm(bracket_model.origin_offset_mm) > 15.0
    cam = Camera(560.0, 560.0, 319.5, 239.5, 640, 480)
    R = view_directions(1)[9].R_m2c
    pose = Pose(R, np.array([30.0, -20.0, 650.0]))
    image = render_scene(renderer, bracket_mesh, cam, pose)
    result = localize(bracket_model, image, cam, LocalizeOptions(refine=refine, min_score=0.0))
    assert result.detections
    det = result.detections[0]
    origin_px = cam.project(pose.t_m2c[None])[0]
    centre_px = cam.project((R @ bracket_model.origin_offset_mm + pose.t_m2c)[None])[0]
    assert np.hypot(*(centre_px - origin_px)) > 15.0
    err_px = np.hypot(det.similarity.x - origin_px[0], det.similarity.y - origin_px[1])
    assert err_px < (3.0 if refine else 8.0)
    # The reference point and the pose agree.
    assert np.allclose(cam.project(det.pose.t_m2c[None])[0],
                       [det.similarity.x, det.similarity.y], atol=1e-6)



def test_the_contour_beyond_the_image_border_counts_as_unconfirmed(
        renderer, bracket_mesh, bracket_model):
    # A fit that puts much of the part outside the image is judged by what is
    # left inside: found at its place, but scored as the share of its whole
    # contour confirmed, as a part hidden by as much would be.
    cam = Camera(560.0, 560.0, 319.5, 239.5, 640, 480)
    R = view_directions(1)[9].R_m2c
    border_x_mm = (cam.width - 1 - cam.cx) * 650.0 / cam.fx
    scores = []
    for x_mm in (0.0, border_x_mm):
        pose = Pose(R, np.array([x_mm, 0.0, 650.0]))
        image = render_scene(renderer, bracket_mesh, cam, pose)
        det = localize(bracket_model, image, cam, LocalizeOptions(min_score=0.0)).detections[0]
        origin_px = cam.project(pose.t_m2c[None])[0]
        assert np.hypot(det.similarity.x - origin_px[0], det.similarity.y - origin_px[1]) < 8.0
        scores.append(det.score)
    inside, cut = scores
    assert inside > 0.7
    assert cut < 0.75 * inside


def test_a_part_in_fog_is_found_as_in_clear_air(renderer, bracket_mesh, bracket_model,
                                                monkeypatch):
    # Fog scales every gradient by the share of light that gets through
    # (here 0.1): the L-bracket's outline falls under a fixed edge floor,
    # not under one that follows the contrast around it. Poses that are
    # found in clear air (measured: 6 of 12 random poses with this coarse
    # model); in fog, with the local floor 6, with the fixed one 0.
    cam = Camera(560.0, 560.0, 319.5, 239.5, 640, 480)
    scenes = []
    for seed in (1, 6, 7, 8, 9, 11):
        pose = Pose(Rotation.random(random_state=seed).as_matrix(),
                    np.array([40.0 * (seed % 3 - 1), 30.0 * (seed % 2), 600.0]))
        clear = render_scene(renderer, bracket_mesh, cam, pose, clutter=3, rng=seed)
        fog = np.clip(0.1 * clear.astype(np.float32) + 0.9 * 215.0, 0, 255).astype(np.uint8)
        scenes.append((fog, pose))

    def found() -> int:
        n = 0
        for image, pose in scenes:
            dets = localize(bracket_model, image, cam).detections
            n += (bool(dets) and np.linalg.norm(dets[0].pose.t_m2c - pose.t_m2c) < 15.0
                  and rotation_angle_deg(dets[0].pose.R_m2c, pose.R_m2c) < 5.0)
        return n

    assert found() >= 5
    monkeypatch.setattr(localize_module, "local_min_gradient",
                        lambda edges, centre, radius, ceiling: ceiling)
    assert found() <= 1


def test_a_grey_image_stored_as_rgb_is_localized_as_the_grey_image(
    renderer, bracket_mesh, bracket_model, monkeypatch
):
    # A monochrome camera's frame stored as RGB carries no colour: it must
    # give the grey image's answer, not fits judged by a chromaticity that
    # is flat everywhere (a figure-ground contrast of 0 that is never
    # settled, so that every image pays for spare fits).
    cam = Camera(560.0, 560.0, 319.5, 239.5, 640, 480)
    pose = Pose(Rotation.random(random_state=3).as_matrix(), np.array([20.0, -10.0, 620.0]))
    grey = render_scene(renderer, bracket_mesh, cam, pose, clutter=3, rng=3).max(axis=2)
    as_rgb = np.repeat(grey[:, :, None], 3, axis=2)
    contrasts: list[float | None] = []
    measure = localize_module.figure_ground_contrast

    def recorded(*args, **kwargs):
        contrasts.append(measure(*args, **kwargs))
        return contrasts[-1]

    monkeypatch.setattr(localize_module, "figure_ground_contrast", recorded)
    from_grey = localize(bracket_model, grey, cam).detections
    from_rgb = localize(bracket_model, as_rgb, cam).detections
    assert from_grey and len(from_rgb) == len(from_grey)
    for a, b in zip(from_grey, from_rgb, strict=True):
        assert a.score == b.score
        assert np.array_equal(a.pose.R_m2c, b.pose.R_m2c)
        assert np.array_equal(a.pose.t_m2c, b.pose.t_m2c)
    assert contrasts and all(c is None for c in contrasts)
    # A scene in colour (here a warm light's tint) is still judged by its colours.
    tinted = (grey[:, :, None] * np.array([1.0, 0.8, 0.5])).astype(np.uint8)
    localize(bracket_model, tinted, cam)
    assert any(c is not None for c in contrasts)


def _fit(score: float, refined: bool, tag: int, chance_corrected: float | None = None,
         evidence: float = 100.0) -> _Fitted:
    """A fitted location told apart by its model view."""
    return _Fitted(Detection(score=score, log_probability=0.0, model_view=tag, azimuth_deg=0.0,
                             polar_deg=0.0, similarity=Similarity2D(0.0, 0.0, 0.0, 1.0),
                             pose=Pose(np.eye(3), np.array([0.0, 0.0, 500.0])),
                             refined=refined), chance_corrected, evidence=evidence)


def test_refined_fits_rank_by_chance_corrected_fraction_then_failed_in_the_view_search_order(
) -> None:
    # At equal evidence, refined fits go by their chance-corrected inlier
    # fraction, not by the plain one (texture); failed refinements last,
    # in the given order.
    in_evidence_order = [
        _fit(0.62, False, 0),
        _fit(0.70, True, 1, chance_corrected=0.40),
        _fit(0.88, True, 2, chance_corrected=0.85),
        _fit(0.95, True, 3, chance_corrected=0.93),
        _fit(0.55, False, 4),
        _fit(0.66, True, 5, chance_corrected=0.60),  # beats 1 on chance, not on score
    ]
    ranked = _ranked(in_evidence_order)
    assert [d.model_view for d in ranked] == [3, 2, 5, 1, 0, 4]
    # As reported, scores never rise down the list; each is its own or the
    # one above's.
    scores = [d.score for d in _non_increasing(ranked)]
    assert scores == [0.95, 0.88, 0.66, 0.66, 0.62, 0.55]
    assert sorted(scores, reverse=True) == scores


def test_a_fit_at_a_place_the_view_search_barely_supports_loses_to_the_right_one() -> None:
    # A refinement started at a wrong place can settle on clutter and
    # confirm a little more of its contour than the part's fit; the view
    # search's evidence for the place (a third of the best) decides.
    right = _fit(0.90, True, 0, chance_corrected=0.86, evidence=270.0)
    clutter = _fit(0.96, True, 1, chance_corrected=0.95, evidence=90.0)
    assert [d.model_view for d in _ranked([right, clutter])] == [0, 1]
    assert [d.model_view for d in _ranked([clutter, right])] == [0, 1]
    # A clearly better contour still wins at less evidence.
    better = _fit(0.99, True, 2, chance_corrected=0.86 + EVIDENCE_WEIGHT * 2 / 3 + 0.02,
                  evidence=90.0)
    assert [d.model_view for d in _ranked([right, better])] == [2, 0]
    # Only the shares count: scaling every evidence changes nothing.
    assert [d.model_view for d in _ranked([replace(right, evidence=2.7),
                                           replace(clutter, evidence=0.9)])] == [0, 1]


def _coloured(fit: _Fitted, agreement: float | None, expected: float = 0.8) -> _Fitted:
    """``fit`` with a colour agreement, in a scene where the part's own
    colours get ``expected``."""
    return replace(fit, colour_agreement=agreement, expected_colour_agreement=expected)


def test_with_a_colour_cue_fits_rank_by_contour_plus_colour_and_off_colour_fits_drop() -> None:
    # A wrong place confirms its contour as well as the right one (real
    # photos in clutter); the colour under the fit decides, and a fit on
    # colours that are not the part's is not reported at all.
    fits = [
        _coloured(_fit(0.93, True, 0, chance_corrected=0.9), 0.60),
        _coloured(_fit(0.80, True, 1, chance_corrected=0.6), 0.85),
        _coloured(_fit(0.97, True, 2, chance_corrected=0.95), MIN_COLOUR_AGREEMENT - 0.01),
        _coloured(_fit(0.70, False, 3), 0.9),
        _fit(0.99, True, 4, chance_corrected=0.99),  # no colour measured
        # Colour enough on its own, but with too little contour confirmed.
        _coloured(_fit(0.60, True, 5, chance_corrected=0.5), 0.7),
    ]
    ranked = _ranked(fits, by_colour=True)
    assert [d.model_view for d in ranked] == [1, 0, 3]
    assert COLOUR_WEIGHT > 0
    assert 0.60 + COLOUR_WEIGHT * 0.7 / 0.8 < MIN_COLOUR_RANK <= 0.93 + COLOUR_WEIGHT * 0.6 / 0.8
    # Without the cue the colour is ignored.
    assert [d.model_view for d in _ranked(fits)][:2] == [4, 2]


def test_a_fits_colour_counts_against_what_the_parts_own_colours_get_in_the_scene() -> None:
    # The same fit, covering the same colours: where the part's colours are
    # common in the scene (a grey can among grey things) they are all a
    # right fit can show, and it is reported; where they are rare, a fit
    # showing that little of them is a look-alike and is dropped.
    fit = _fit(0.80, True, 0, chance_corrected=0.7)
    assert [d.model_view for d in _ranked([_coloured(fit, 0.55, expected=0.55)],
                                          by_colour=True)] == [0]
    assert _ranked([_coloured(fit, 0.55, expected=0.92)], by_colour=True) == []
    # Fits of one scene still rank by their colour.
    other = _fit(0.80, True, 1, chance_corrected=0.7)
    ranked = _ranked([_coloured(fit, 0.5, 0.55), _coloured(other, 0.6, 0.55)], by_colour=True)
    assert [d.model_view for d in ranked] == [1, 0]


def test_colour_fits_of_places_rank_lower_when_the_parts_colour_runs_on_beyond_them() -> None:
    # Two places whose contour and colour rank alike: the one with the
    # part's colour running on beyond its outline (a fit shifted onto the
    # part's visible half, or on a larger region of its colours) ranks
    # second, by its excess over the floor, scaled by how rare the part's
    # colours are in the scene.
    inside = _coloured(_fit(0.80, True, 0, chance_corrected=0.7), 0.85, expected=0.9)
    beside = _coloured(_fit(0.82, True, 1, chance_corrected=0.7), 0.85, expected=0.9)
    leak = COLOUR_LEAK_FLOOR + 0.1
    assert [d.model_view for d in _ranked([inside, beside], by_colour=True)] == [1, 0]
    beside = replace(beside, colour_leak=leak)
    inside = replace(inside, colour_leak=COLOUR_LEAK_FLOOR)
    assert inside.colour_leak_penalty == 0.0
    assert beside.colour_leak_penalty == pytest.approx(COLOUR_LEAK_WEIGHT * 0.8 * 0.1)
    assert [d.model_view for d in _ranked([inside, beside], by_colour=True)] == [0, 1]
    # Around a part of common colours the ring is part-like anyway: no penalty.
    common = [replace(f, expected_colour_agreement=0.5, colour_agreement=0.47)
              for f in (inside, beside)]
    assert common[1].colour_leak_penalty == 0.0
    assert [d.model_view for d in _ranked(common, by_colour=True)] == [1, 0]
    # Under COLOUR_LEAK_MAX it orders fits only: alone, the leaking fit is
    # still reported.
    assert leak < COLOUR_LEAK_MAX
    assert [d.model_view for d in _ranked([beside], by_colour=True)] == [1]
    # Without a colour cue nothing is measured and nothing taken.
    assert _fit(0.8, True, 2, chance_corrected=0.7).colour_leak_penalty == 0.0


def test_a_fit_beyond_whose_outline_the_parts_rare_colours_run_on_is_not_reported() -> None:
    # The part's colours are rare in the scene (its own colours get 0.9):
    # a ring just outside the outline holding half of that agreement puts
    # the fit on a larger region of those colours, not on the part.
    rare = _coloured(_fit(0.85, True, 0, chance_corrected=0.8), 0.85, expected=0.9)
    assert rare.colour_rarity == pytest.approx(0.8)
    assert rare.colour_rarity >= COLOUR_LEAK_MIN_RARITY
    within = replace(rare, colour_leak=COLOUR_LEAK_MAX - 0.01)
    beyond = replace(_coloured(_fit(0.95, True, 1, chance_corrected=0.9), 0.9, expected=0.9),
                     colour_leak=COLOUR_LEAK_MAX)
    assert not within.leaks_rare_colour and beyond.leaks_rare_colour
    assert [d.model_view for d in _ranked([within, beyond], by_colour=True)] == [0]
    assert _ranked([beyond], by_colour=True) == []
    # Around a part of common colours (its own get 0.7: rarity 0.4) the ring
    # is part-like whether the fit is right or not: the fit stays.
    common = replace(beyond, colour_agreement=0.7, expected_colour_agreement=0.7,
                     colour_leak=0.9)
    assert common.colour_rarity < COLOUR_LEAK_MIN_RARITY and not common.leaks_rare_colour
    assert [d.model_view for d in _ranked([common], by_colour=True)] == [1]
    # Without a ring measured (off the image) nothing is taken; without
    # the colour cue nothing is gated.
    assert not replace(beyond, colour_leak=None).leaks_rare_colour
    assert [d.model_view for d in _ranked([beyond])] == [1]


def test_a_fit_beside_the_part_has_its_colour_just_outside_the_outline(orange_scene) -> None:
    # The orange bracket among boxes: at its true pose the ring just outside
    # its outline holds little orange; moved a third of its size across the
    # image, its outline cuts through the part and the ring holds the rest.
    shading, camera, truth = orange_scene
    assert shading.colour is not None
    at_truth = shading.colour.leak(camera, truth, shading.samples)
    step_mm = 0.3 * shading.samples.extent_mm
    beside = shading.colour.leak(camera, Pose(truth.R_m2c, truth.t_m2c + [0.0, step_mm, 0.0]),
                                 shading.samples)
    assert at_truth is not None and beside is not None
    assert at_truth < COLOUR_LEAK_FLOOR < beside
    assert beside > at_truth + 0.1
    # A part wholly outside the image has no ring to read.
    away = Pose(truth.R_m2c, truth.t_m2c + [10.0 * truth.t_m2c[2], 0.0, 0.0])
    assert shading.colour.leak(camera, away, shading.samples) is None


@settings(max_examples=60, deadline=None)
@given(st.floats(0.05, 60.0))
def test_colour_offsets_leave_no_point_of_their_square_beyond_the_fits_reach(reach: float) -> None:
    from viewloc_core.localize import _colour_offsets
    from viewloc_core.view_search import FIT_RADII_PX

    offsets = _colour_offsets(reach)
    side = round(math.sqrt(len(offsets)))
    assert side * side == len(offsets) and side % 2 == 1 and side >= 3
    # A square grid over the reach each way, centred on the seed.
    assert np.allclose(offsets.min(axis=0), -reach) and np.allclose(offsets.max(axis=0), reach)
    assert any(np.allclose(o, 0.0) for o in offsets)
    # Every point of the square lies within the fit's first reach of an
    # offset: the worst lie midway between four of them.
    step = 2.0 * reach / (side - 1)
    assert step / math.sqrt(2.0) <= FIT_RADII_PX[0] + 1e-9
    points = np.random.default_rng(0).uniform(-reach, reach, (400, 2))
    nearest = np.min(np.linalg.norm(points[:, None] - offsets[None], axis=2), axis=1)
    assert nearest.max() <= FIT_RADII_PX[0] + 1e-9
    # And no more of them than that takes: one step fewer each way would
    # leave the middle of a cell beyond it (three by three at the least).
    if side > 3:
        coarser = 2.0 * reach / (side - 3)
        assert coarser / math.sqrt(2.0) > FIT_RADII_PX[0]


def test_colour_offsets_are_three_by_three_for_a_small_part_and_finer_for_a_large_one(
) -> None:
    from viewloc_core.localize import COLOUR_OFFSET_SHARE, _colour_offsets

    # A 50 px part: 5 px each way, the former 3x3 grid a tenth of its
    # diameter apart; a 150 px part (LM-O's driller on the searched level):
    # 7x7, 5 px apart.
    small = _colour_offsets(COLOUR_OFFSET_SHARE * 50.0)
    assert len(small) == 9
    assert np.allclose(np.unique(small[:, 0]), [-5.0, 0.0, 5.0])
    large = _colour_offsets(COLOUR_OFFSET_SHARE * 150.0)
    assert len(large) == 49
    assert np.allclose(np.diff(np.unique(large[:, 0])), 5.0)


def test_spare_locations_are_the_next_ones_with_enough_of_the_best_evidence() -> None:
    sim = np.array([100.0, 100.0, 0.0, 1.0])

    def located(evidence: float) -> _Located:
        return _Located(Match2D(0, sim, 0.0, 0.9, 10, evidence),
                        [ViewCandidate(0, sim, evidence, 0.9)])

    # Best first, as the view search ranks them.
    best = 300.0
    places = [located(e) for e in (best, 250.0, SPARE_MIN_VIEW_EVIDENCE_SHARE * best,
                                   0.99 * SPARE_MIN_VIEW_EVIDENCE_SHARE * best, 100.0)]
    assert _spare_locations(places, 1, 2) == places[1:3]
    assert _spare_locations(places, 1, 3) == places[1:3]
    assert _spare_locations(places, 2, 3) == [places[2]]
    assert _spare_locations(places, 5, 2) == []
    assert _spare_locations([], 1, 2) == []


def test_a_spare_location_competes_only_with_a_convincing_refinement() -> None:
    # A high plain inlier fraction is not enough (texture), nor is a fit
    # whose refinement failed; the chance-corrected fraction decides.
    assert not _convincing(_fit(0.95, False, 0))
    assert not _convincing(_fit(0.90, True, 1, chance_corrected=SPARE_MIN_CHANCE_CORRECTED - 0.01))
    assert _convincing(_fit(0.75, True, 2, chance_corrected=SPARE_MIN_CHANCE_CORRECTED))
    # In a colour scene, whose colour proposes locations of its own, the bar is higher.
    assert SPARE_MIN_CHANCE_CORRECTED_IN_COLOUR > SPARE_MIN_CHANCE_CORRECTED
    assert not _convincing(_fit(0.75, True, 2, chance_corrected=SPARE_MIN_CHANCE_CORRECTED),
                           in_colour=True)
    assert _convincing(_fit(0.8, True, 3, chance_corrected=SPARE_MIN_CHANCE_CORRECTED_IN_COLOUR),
                       in_colour=True)


def test_a_request_accepting_less_of_the_contour_holds_spares_to_a_bar_lowered_alike() -> None:
    # A part a third hidden, fitted at a spare location: 0.65 of its contour
    # confirmed, 0.56 beyond chance. The default bar keeps it out; a request
    # whose min_score is 5/6 of the model's default lowers the bar to 5/6.
    hidden = _fit(0.65, True, 1, chance_corrected=0.56)
    assert not _convincing(hidden)
    share = _spare_bar_share(0.5, 0.6)
    assert share == pytest.approx(0.5 / 0.6)
    assert _convincing(hidden, bar_share=share)
    assert not _convincing(_fit(0.6, True, 2, chance_corrected=0.49), bar_share=share)
    # The default, or a stricter min_score, leaves the bar as it is.
    assert _spare_bar_share(0.6, 0.6) == 1.0
    assert _spare_bar_share(0.9, 0.6) == 1.0
    assert not _convincing(hidden, bar_share=_spare_bar_share(0.9, 0.6))
    # The colour scenes' higher bar is lowered in the same proportion.
    coloured = _fit(0.8, True, 3, chance_corrected=SPARE_MIN_CHANCE_CORRECTED_IN_COLOUR * share)
    assert not _convincing(coloured, in_colour=True)
    assert _convincing(coloured, in_colour=True, bar_share=share)
    # A model without a default bar leaves it whole.
    assert _spare_bar_share(0.3, 0.0) == 1.0


def test_a_colour_location_only_its_colours_outline_explains_is_held_to_the_spares_bar(
) -> None:
    # Colour locations found on the photo's edges compete whatever their
    # fit; one whose views only the outline of the part's colour explains
    # competes with a fit convincing in colour (lowered with the request's
    # min_score, as a spare's).
    sim = np.array([100.0, 100.0, 0.0, 1.0])

    def located(outline_only: bool) -> _Located:
        return _Located(Match2D(0, sim, 0.0, 0.9, 10, 50.0), [ViewCandidate(0, sim, 50.0, 0.9)],
                        outline_only=outline_only)

    bar = SPARE_MIN_CHANCE_CORRECTED_IN_COLOUR
    weak = _fit(0.8, True, 0, chance_corrected=bar - 0.05)
    convincing = _fit(0.8, True, 1, chance_corrected=bar)
    failed = _fit(0.8, False, 2)
    fits = [weak, convincing, failed]
    assert _supported(fits, [located(False)] * 3, 1.0) == fits
    assert _supported(fits, [located(True)] * 3, 1.0) == [convincing]
    assert _supported(fits, [located(True), located(False), located(True)], 1.0) == [convincing]
    assert _supported(fits, [located(True)] * 3, (bar - 0.06) / bar) == [weak, convincing]
    assert _supported([], [], 1.0) == []


def test_detections_after_the_first_are_held_to_the_spares_bar() -> None:
    # The best fit is reported on its own merits; each further one must
    # confirm its contour beyond chance as a spare location's fit must, or
    # it is dropped (and its place goes to the next location).
    best = _fit(0.80, True, 0, chance_corrected=0.55)
    copy = _fit(0.90, True, 1, chance_corrected=SPARE_MIN_CHANCE_CORRECTED)
    weak = _fit(0.70, True, 2, chance_corrected=SPARE_MIN_CHANCE_CORRECTED - 0.05)
    failed = _fit(0.75, False, 3)
    fits = [best, copy, weak, failed]
    ranked = [f.detection for f in fits]
    kept = _after_the_first_convincing(ranked, fits, in_colour=False, bar_share=1.0)
    assert [d.model_view for d in kept] == [0, 1]
    # The weak fit passes a bar lowered for a request accepting less of the
    # contour; a failed refinement never does.
    lowered = _after_the_first_convincing(ranked, fits, in_colour=False, bar_share=0.9)
    assert [d.model_view for d in lowered] == [0, 1, 2]
    # In colour the bar is the colour scenes' spares' bar.
    assert [d.model_view for d in _after_the_first_convincing(
        ranked, fits, in_colour=True, bar_share=1.0)] == [0]
    # Whatever its own fit, the first stays first, alone or not.
    assert _after_the_first_convincing(ranked[2:], fits, False, 1.0) == ranked[2:3]
    assert _after_the_first_convincing(ranked[3:], fits, False, 1.0) == ranked[3:]
    assert _after_the_first_convincing([], fits, False, 1.0) == []


def test_a_fit_hidden_behind_a_better_confirmed_one_ranks_after_the_rest() -> None:
    # A block 120 x 80 x 40 mm face on at 600 mm, and a far copy of it (2400
    # mm) whose outline lies inside the near one's, fitted to its inner
    # edges: ranked first (by colour, say), it goes after every fit not
    # hidden, whatever their order. A copy at 1200 mm beside the near one's
    # outline is not hidden; nor is a far copy whose cover confirms less of
    # its contour.
    mesh = trimesh.creation.box((120.0, 80.0, 40.0))
    samples = surface_samples(np.asarray(mesh.vertices), np.asarray(mesh.faces))
    camera = Camera(600.0, 600.0, 319.5, 239.5, 640, 480)
    offset = np.array([0.0, 0.0, 10.0])  # the model's origin 10 mm off its centre

    def placed(score: float, tag: int, centre_mm: tuple[float, float, float],
               refined: bool = True) -> Detection:
        det = _fit(score, refined, tag).detection
        return replace(det, pose=Pose(np.eye(3), np.array(centre_mm) - offset))

    far = placed(0.70, 0, (10.0, 0.0, 2400.0))
    near = placed(0.95, 1, (0.0, 0.0, 600.0))
    beside = placed(0.80, 2, (400.0, 0.0, 1200.0))
    ranked = _visible_first([far, beside, near], offset, camera, samples)
    assert [d.model_view for d in ranked] == [2, 1, 0]
    # The near fit confirming less, or unrefined: nothing moves.
    weaker = replace(near, score=0.65)
    assert _visible_first([far, beside, weaker], offset, camera, samples) == [far, beside, weaker]
    unrefined = replace(near, refined=False)
    assert _visible_first([far, unrefined], offset, camera, samples) == [far, unrefined]
    # Without the part's surface (no mesh) the ranking stands.
    assert _visible_first([far, near], offset, camera, None) == [far, near]


def test_a_fit_that_stands_out_from_its_surroundings_outranks_a_shadow_like_one() -> None:
    # Two confirmed outlines (the part, and its cast shadow a little better
    # confirmed): the one whose inside differs in colour from its
    # surroundings wins. Among unconfirmed fits the contrast adds to the
    # chance-corrected fraction alike. A clearly better contour still wins.
    shadow = replace(_fit(0.97, True, 0, chance_corrected=0.96), figure_ground=0.01)
    part = replace(_fit(0.93, True, 1, chance_corrected=0.92), figure_ground=0.35)
    assert [d.model_view for d in _ranked([shadow, part])] == [1, 0]
    texture = replace(_fit(0.75, True, 2, chance_corrected=0.70), figure_ground=0.0)
    faint = replace(_fit(0.72, True, 3, chance_corrected=0.65), figure_ground=0.2)
    assert [d.model_view for d in _ranked([texture, faint])] == [3, 2]
    better = replace(_fit(0.99, True, 4, chance_corrected=0.92 + FIGURE_GROUND_WEIGHT + 0.01),
                     figure_ground=0.0)
    assert [d.model_view for d in _ranked([part, better])] == [4, 1]
    # A contrast beyond FIGURE_GROUND_FULL counts no more; none counts nothing.
    full = replace(part, figure_ground=FIGURE_GROUND_FULL)
    assert full.figure_ground_bonus == part.figure_ground_bonus == FIGURE_GROUND_WEIGHT
    assert _fit(0.9, True, 5, chance_corrected=0.9).figure_ground_bonus == 0.0


def test_a_confirmed_fit_that_looks_like_its_surroundings_gets_a_spare_beside_it() -> None:
    assert _settled(replace(_fit(0.95, True, 0, chance_corrected=0.9),
                            figure_ground=FIRST_FIT_MIN_FIGURE_GROUND))
    assert not _settled(replace(_fit(0.95, True, 0, chance_corrected=0.9),
                                figure_ground=FIRST_FIT_MIN_FIGURE_GROUND - 0.01))
    # No colour (grey image, or no surface seen): the contour decides alone.
    assert _settled(_fit(0.95, True, 0, chance_corrected=0.9))
    assert not _settled(replace(_fit(GOOD_FIT_FRACTION - 0.01, True, 0, chance_corrected=0.8),
                                figure_ground=0.5))
    # On texture a wrong fit confirms its contour plainly, not beyond chance.
    assert not _settled(replace(_fit(0.95, True, 0,
                                     chance_corrected=GOOD_FIT_FRACTION - 0.01),
                                figure_ground=0.5))


def test_a_smooth_part_is_turned_the_right_way_by_its_shading(renderer, monkeypatch):
    # An egg-like part's outline fits from views far apart (its front and
    # back mirror each other's outline); what tells them apart is how the
    # light falls on it. 40 random poses under two lightings: measured 26
    # within 10 deg, 22 with the shading cue switched off (24 poses: 16
    # and 14, too few to tell the cue from the luck of the 2D stage).
    mesh = blob()
    model = learn_from_mesh(mesh, LearningConfig(max_level=1, min_level=1))
    cam = Camera(600.0, 600.0, 319.5, 239.5, 640, 480)
    prepared = prepare(mesh)
    scenes = []
    for seed in range(40):
        R = Rotation.random(random_state=100 + seed).as_matrix()
        pose = Pose(R, np.array([40.0 * ((seed % 3) - 1), 20.0, 500.0]))
        out = renderer.render(prepared, cam, pose, lights=LIGHTS[seed % 2],
                              background_rgb=(30, 30, 30))
        scenes.append((out.color, R))

    def right_way(weight: float) -> int:
        monkeypatch.setattr(localize_module, "SHADING_WEIGHT", weight)
        n = 0
        for image, R in scenes:
            found = localize(model, image, cam).detections
            n += bool(found) and rotation_angle_deg(found[0].pose.R_m2c, R) < 10.0
        return n

    with_shading = right_way(localize_module.SHADING_WEIGHT)
    assert with_shading >= 24
    assert with_shading >= right_way(0.0) + 3


def test_shading_decides_between_contour_shares_a_grey_image_leaves_close(
        orange_scene, monkeypatch):
    # Measured on the hard bench set in grey (free-form part): the part
    # turned over confirmed 0.990 of its outline with a shading agreement of
    # 0.838, the truth 0.984 with 0.885. The truth must rank higher; a
    # contour confirmed clearly better (5 % more) still outranks shading.
    shading, camera, truth = orange_scene
    plain = replace(shading, colour=None, interior=None)
    turned = Pose(truth.R_m2c @ Rotation.from_euler("y", 180.0, degrees=True).as_matrix(),
                  truth.t_m2c)
    agreement = {id(truth): 0.885, id(turned): 0.838}
    monkeypatch.setattr(localize_module, "shading_agreement",
                        lambda image, camera, pose, samples, visible: agreement[id(pose)])
    truth_rank = plain.rank(camera, RefinementResult(truth, True, 10, 0.5, 0.984))
    assert truth_rank > plain.rank(camera, RefinementResult(turned, True, 10, 0.5, 0.990))
    assert truth_rank < plain.rank(camera, RefinementResult(turned, True, 10, 0.5, 0.984 + 0.05))


@pytest.fixture(scope="module")
def orange_scene(renderer, orange_model):
    """The ranking of fits in a scene of the orange bracket among boxes,
    with every cue on (shading, colour, interior edges): the
    :class:`_Shading`, the camera and the true pose."""
    camera = Camera(600.0, 600.0, 319.5, 239.5, 640, 480)
    truth = Pose(Rotation.from_euler("xyz", [0.5, -0.4, 0.9]).as_matrix(),
                 np.array([10.0, -5.0, 420.0]))
    image = render_scene(renderer, coloured_bracket(ORANGE), camera, truth, clutter=6)
    contour = _contour_model(orange_model)
    surface = _surface(orange_model)
    colour = _ColourScene.of(orange_model, image, 1.0)
    assert contour is not None and surface is not None and colour is not None
    interior = _Interior(extract_features(image).edge_distance, 1.0, contour)
    return _Shading(image, *surface, colour, interior), camera, truth


@settings(max_examples=40, deadline=None)
@given(inliers=st.floats(0.0, 1.0), turn_deg=st.floats(0.0, 180.0),
       short_of=st.floats(-1.5, 1.5))
def test_a_ranking_stops_early_only_for_a_fit_below_the_rank_it_must_reach(
        orange_scene, inliers, turn_deg, short_of):
    # A fit turned away from the truth, with any share of its contour
    # confirmed, asked to reach its own full rank plus ``short_of``: it gets
    # that rank, or -inf when the rank is below what it must reach.
    shading, camera, truth = orange_scene
    turn = Rotation.from_rotvec(np.radians(turn_deg) * np.array([0.6, 0.8, 0.0])).as_matrix()
    fit = RefinementResult(Pose(truth.R_m2c @ turn, truth.t_m2c), True, 10, 0.5, inliers)
    full = shading.rank(camera, fit)
    bounded = shading.rank(camera, fit, at_least=full + short_of)
    if short_of <= 0.0:
        assert bounded == full
    else:
        assert bounded in (full, -math.inf)


@pytest.mark.parametrize(("bound_after", "read_before"),
                         [("contour", []), ("colour", ["colour"]),
                          ("shading", ["colour", "shading"])])
def test_a_ranking_reads_no_cue_once_the_rank_it_must_reach_is_out_of_reach(
        orange_scene, monkeypatch, bound_after, read_before):
    # With every cue at most 1, a fit confirming 0.2 of its contour ranks
    # at most 0.2 + SHADING_WEIGHT + COLOUR_WEIGHT; with its colour read, at
    # most 0.2 + SHADING_WEIGHT + that colour; with its shading read too,
    # at most its rank without the interior edges (which only lower it).
    # Asked for a hair more than such a bound, the ranking reads no further
    # cue; for a hair less, it reads the next one.
    shading, camera, truth = orange_scene
    fit = RefinementResult(truth, True, 10, 0.5, 0.2)
    colour = shading.colour.agreement(camera, truth, shading.samples)
    bound = {"contour": 0.2 + SHADING_WEIGHT + COLOUR_WEIGHT,
             "colour": 0.2 + SHADING_WEIGHT + COLOUR_WEIGHT * colour,
             "shading": replace(shading, interior=None).rank(camera, fit)}[bound_after]
    full = shading.rank(camera, fit)
    read: list[str] = []

    def spy(name, function):
        def read_cue(*args, **kwargs):
            read.append(name)
            return function(*args, **kwargs)
        return read_cue

    monkeypatch.setattr(_ColourScene, "agreement", spy("colour", _ColourScene.agreement))
    monkeypatch.setattr(localize_module, "shading_agreement",
                        spy("shading", localize_module.shading_agreement))
    monkeypatch.setattr(_Interior, "explained_share",
                        spy("interior", _Interior.explained_share))
    assert shading.rank(camera, fit, at_least=bound + 1e-6) == -math.inf
    assert read == read_before
    read.clear()
    assert shading.rank(camera, fit, at_least=bound - 1e-6) in (full, -math.inf)
    next_cue = {"contour": "colour", "colour": "shading", "shading": "interior"}[bound_after]
    assert read[len(read_before)] == next_cue


def _two_views_at_one_location(model):
    """A camera, a location whose view search found training view 0 and,
    second, a view over 60° from it, both at the image centre, and the
    similarity that puts them there: (camera, first, other, sim, loc)."""
    camera = Camera(600.0, 600.0, 319.5, 239.5, 640, 480)
    tr = model.training
    first_view = 0
    other_view = next(v for v in range(len(tr.R_m2c))
                      if rotation_angle_deg(tr.R_m2c[v], tr.R_m2c[first_view]) > 60.0)
    sim = Similarity2D(320.0, 240.0, 0.0, 1.0)
    sim_array = np.array([320.0, 240.0, 0.0, 1.0])
    loc = _Located(Match2D(0, sim_array, 0.0, 0.9, 10, 100.0),
                   [ViewCandidate(v, sim_array, 100.0, 0.9) for v in (first_view, other_view)])
    return camera, first_view, other_view, sim, loc


@pytest.mark.parametrize(("near_symmetric", "quick_fraction", "wins"),
                         [(True, 0.80, True), (False, 0.80, False), (True, 0.70, False)])
def test_a_near_symmetric_parts_best_other_start_gets_the_full_fit(
        bracket_model, monkeypatch, near_symmetric, quick_fraction, wins):
    # The quick fit of a start (few iterations, half the points) can rank
    # below the full fit it competes with, even where its own full fit
    # ranks higher.
    # Here refinement leaves every pose where it is and confirms
    # ``quick_fraction`` of the contour quickly, 0.95 fully; the first fit
    # confirmed 0.90. A part with near-symmetries gets the other start's
    # full fit, and it wins, unless the quick fit falls more than
    # NEAR_SYMMETRIC_MAX_SHORT_FIT_GAP short of the first fit; a part
    # without them keeps the first fit (its quick rival ranks lower).
    assert 0.90 - 0.80 < localize_module.NEAR_SYMMETRIC_MAX_SHORT_FIT_GAP < 0.90 - 0.70
    model = bracket_model
    camera, first_view, other_view, sim, loc = _two_views_at_one_location(model)
    full_fits = []

    def refine(edges, camera_, start, contour, options):
        quick = options is localize_module.QUICK_REFINE
        if not quick:
            full_fits.append(start)
        return RefinementResult(start, True, 3, 0.5, quick_fraction if quick else 0.95)

    class Shading:
        near = NearSymmetries(np.eye(4)[None] if near_symmetric else np.zeros((0, 4, 4)),
                              np.ones(1 if near_symmetric else 0))

        def rank(self, camera_, result, at_least=-math.inf):
            return result.inlier_fraction

    monkeypatch.setattr(localize_module, "refine_pose", refine)
    monkeypatch.setattr(NearSymmetries, "twins", lambda self, pose: [])
    # One start per view: the other view is not also tried at other depths.
    monkeypatch.setattr(localize_module, "RIVAL_SCALE_FACTORS", ())
    start = _pose_centred(model, first_view, sim, camera)
    first = RefinementResult(start, True, 10, 0.5, 0.90)
    result, view, _, _ = _other_sides(model, loc, 1.0, camera, None, None, Shading(),
                                      first_view, sim, start, first, _FitOptions())
    assert (view, result.inlier_fraction) == ((other_view, 0.95) if wins
                                              else (first_view, 0.90))
    assert len(full_fits) == (1 if wins else 0)


def _runner_up_and_its_twin(model):
    """Two views at one location (:func:`_two_views_at_one_location`), a
    near-symmetry of the part (a half turn about its z axis), the first
    view's pose, the runner-up view's pose and that pose's twin (the truth
    of the tests that use it): (camera, first_view, other_view, sim, loc,
    near, first_pose, runner_up, truth)."""
    camera, first_view, other_view, sim, loc = _two_views_at_one_location(model)
    half_turn = np.eye(4)
    half_turn[:3, :3] = Rotation.from_rotvec([0.0, 0.0, np.pi]).as_matrix()
    near = NearSymmetries(half_turn[None], np.ones(1))
    first_pose = _pose_centred(model, first_view, sim, camera)
    runner_up = _pose_centred(model, other_view, sim, camera)
    return (camera, first_view, other_view, sim, loc, near, first_pose, runner_up,
            near.twins(runner_up)[0])


class _RankedByRotation:
    """A fake :class:`_Shading` with the part's near-symmetries ``near``: a
    fit ranks as the first of ``ranks`` ((pose, rank) pairs) whose rotation
    is within 1° of its own, ``otherwise`` when none is."""

    def __init__(self, near: NearSymmetries, ranks: list[tuple[Pose, float]],
                 otherwise: float) -> None:
        self.near = near
        self.ranks = ranks
        self.otherwise = otherwise

    def rank(self, camera, result, at_least=-math.inf):
        for pose, rank in self.ranks:
            if rotation_angle_deg(result.pose.R_m2c, pose.R_m2c) < 1.0:
                return rank
        return self.otherwise


def _refine_in_place(edges, camera, start, contour, options):
    """A refinement that leaves every pose where it is, confirming 0.9."""
    return RefinementResult(start, True, 3, 0.5, 0.9)


@pytest.mark.parametrize("rounds", [1, 2])
def test_a_winning_rivals_own_twin_is_tried_in_the_next_round(bracket_model, monkeypatch,
                                                              rounds):
    # The truth is the half turn of a runner-up view, which is not a twin of
    # the first fit. Round one: the runner-up beats the first fit and its
    # twin. Round two: the runner-up's own twin, the truth, beats it.
    # Refinement leaves every pose where it is; the rank says how near a
    # pose is to the truth or to the runner-up.
    model = bracket_model
    camera, first_view, other_view, sim, loc, half_turns, first_pose, runner_up, truth = (
        _runner_up_and_its_twin(model))

    shading = _RankedByRotation(half_turns, [(truth, 1.0), (runner_up, 0.8)], 0.5)
    monkeypatch.setattr(localize_module, "refine_pose", _refine_in_place)
    monkeypatch.setattr(localize_module, "OTHER_SIDE_ROUNDS", rounds)
    first = RefinementResult(first_pose, True, 10, 0.5, 0.9)
    result, view, _, _ = _other_sides(model, loc, 1.0, camera, None, None, shading,
                                      first_view, sim, first_pose, first, _FitOptions())
    assert view == other_view
    expected = truth if rounds == 2 else runner_up
    assert rotation_angle_deg(result.pose.R_m2c, expected.R_m2c) < 1e-6


@pytest.mark.parametrize("short_by", [0.05, 0.2])
def test_a_losing_runner_ups_twin_is_tried_when_it_lost_narrowly(bracket_model, monkeypatch,
                                                                 short_by):
    # The truth is the half turn of a runner-up view that ranks ``short_by``
    # below the first fit. Round one: nothing beats the first fit (its own
    # twin ranks low). Round two tries the runner-up's twin, the truth, when
    # the runner-up lost by less than NEAR_SYMMETRIC_MAX_SHORT_FIT_GAP.
    gap = localize_module.NEAR_SYMMETRIC_MAX_SHORT_FIT_GAP
    assert 0.05 < gap < 0.2
    model = bracket_model
    camera, first_view, other_view, sim, loc, half_turns, first_pose, runner_up, truth = (
        _runner_up_and_its_twin(model))

    shading = _RankedByRotation(
        half_turns, [(truth, 1.0), (runner_up, 0.9 - short_by), (first_pose, 0.9)], 0.5)
    monkeypatch.setattr(localize_module, "refine_pose", _refine_in_place)
    monkeypatch.setattr(localize_module, "RIVAL_SCALE_FACTORS", ())
    first = RefinementResult(first_pose, True, 10, 0.5, 0.9)
    result, _, _, _ = _other_sides(model, loc, 1.0, camera, None, None, shading,
                                   first_view, sim, first_pose, first, _FitOptions())
    expected = truth if short_by < gap else first_pose
    assert rotation_angle_deg(result.pose.R_m2c, expected.R_m2c) < 1e-6


def test_a_part_without_near_symmetries_is_turned_over_about_its_outlines_axes(
        bracket_model, monkeypatch):
    # The L-bracket has no near-symmetry, but its outline can be nearly
    # symmetric about an axis in the image: the truth is the first fit
    # turned over about the line of sight, which only an outline turn
    # reaches. Refinement leaves every pose where it is.
    model = bracket_model
    surface = localize_module._surface(model)
    assert surface is not None and len(surface[1].transforms) == 0
    camera, first_view, _, sim, loc = _two_views_at_one_location(model)
    loc = _Located(loc.match, loc.candidates[:1])
    first_pose = _pose_centred(model, first_view, sim, camera)
    truth = surface[1].outline_turns(first_pose)[2]

    shading = _RankedByRotation(surface[1], [(truth, 1.0)], 0.8)
    monkeypatch.setattr(localize_module, "refine_pose", _refine_in_place)
    first = RefinementResult(first_pose, True, 10, 0.5, 0.9)
    result, view, _, _ = _other_sides(model, loc, 1.0, camera, None, None, shading,
                                      first_view, sim, first_pose, first, _FitOptions())
    assert view == first_view
    assert rotation_angle_deg(result.pose.R_m2c, truth.R_m2c) < 1e-6


@pytest.mark.parametrize("factors", [(), localize_module.RIVAL_SCALE_FACTORS])
def test_a_rival_view_is_also_tried_nearer_and_farther(bracket_model, monkeypatch, factors):
    # The view search finds the runner-up view (the truth's) a few % off in
    # scale, farther than a short fit pulls it in depth. Refinement leaves
    # every pose where it is; the rank says how near a pose is to the truth,
    # the runner-up's view at the first scale factor's depth. The first fit
    # ranks between the truth and the runner-up at its searched depth.
    model = bracket_model
    camera, first_view, other_view, sim, loc = _two_views_at_one_location(model)
    truth_factor = localize_module.RIVAL_SCALE_FACTORS[0]
    monkeypatch.setattr(localize_module, "RIVAL_SCALE_FACTORS", factors)
    truth = _pose_centred(model, other_view, replace(sim, scale=sim.scale * truth_factor),
                          camera)

    class Shading:
        near = NearSymmetries(np.zeros((0, 4, 4)), np.ones(0))

        def rank(self, camera_, result, at_least=-math.inf):
            R, t = result.pose.R_m2c, result.pose.t_m2c
            if rotation_angle_deg(R, truth.R_m2c) > 1.0:
                return 0.8
            return 1.0 if abs(t[2] - truth.t_m2c[2]) < 1e-6 * truth.t_m2c[2] else 0.5

    monkeypatch.setattr(localize_module, "refine_pose", _refine_in_place)
    monkeypatch.setattr(NearSymmetries, "twins", lambda self, pose: [])
    first_pose = _pose_centred(model, first_view, sim, camera)
    first = RefinementResult(first_pose, True, 10, 0.5, 0.9)
    result, view, similarity, start = _other_sides(model, loc, 1.0, camera, None, None,
                                                   Shading(), first_view, sim, first_pose,
                                                   first, _FitOptions())
    if factors:
        assert view == other_view
        assert similarity.scale == pytest.approx(sim.scale * truth_factor)
        # Nearer or farther, the start keeps its image position and view.
        assert np.allclose(camera.project(start.t_m2c[None]),
                           camera.project(first_pose.t_m2c[None]))
        assert rotation_angle_deg(result.pose.R_m2c, truth.R_m2c) < 1e-6
        assert result.pose.t_m2c[2] > first_pose.t_m2c[2]
    else:
        assert (view, result.pose) == (first_view, first_pose)


@pytest.mark.parametrize("above_the_bar", [True, False])
def test_a_runner_up_view_competes_from_its_share_of_the_best_views_evidence(
        bracket_model, monkeypatch, above_the_bar):
    # The runner-up view is the truth (it ranks higher once fitted); it gets
    # its fit when its evidence is at least OTHER_VIEW_EVIDENCE_SHARE of the
    # best view's, and not below.
    model = bracket_model
    camera, first_view, other_view, sim, loc = _two_views_at_one_location(model)
    share = localize_module.OTHER_VIEW_EVIDENCE_SHARE + (0.01 if above_the_bar else -0.01)
    runner_up = replace(loc.candidates[1], log_likelihood_ratio=share * loc.evidence)
    loc = _Located(loc.match, [loc.candidates[0], runner_up])
    truth = _pose_centred(model, other_view, sim, camera)
    shading = _RankedByRotation(NearSymmetries(np.zeros((0, 4, 4)), np.ones(0)),
                                [(truth, 1.0)], 0.8)
    monkeypatch.setattr(localize_module, "refine_pose", _refine_in_place)
    monkeypatch.setattr(NearSymmetries, "twins", lambda self, pose: [])
    first_pose = _pose_centred(model, first_view, sim, camera)
    first = RefinementResult(first_pose, True, 10, 0.5, 0.9)
    _, view, _, _ = _other_sides(model, loc, 1.0, camera, None, None, shading, first_view,
                                 sim, first_pose, first, _FitOptions())
    assert view == (other_view if above_the_bar else first_view)


@pytest.mark.parametrize("wins", [True, False])
def test_the_wider_look_fits_the_views_its_location_did_not_have(bracket_model, monkeypatch,
                                                                 wins):
    # A reported detection's location is searched again for more views. The
    # location had only the first view; the wider search returns it and
    # another view, the truth's when ``wins``. Only the other view is
    # fitted: neither the location's own view again nor, in that first
    # round, the first fit's outline turns (it won against them already).
    # Refinement leaves every pose where it is; the first fit ranks 0.8.
    model = bracket_model
    camera, first_view, other_view, sim, loc = _two_views_at_one_location(model)
    loc = _Located(loc.match, loc.candidates[:1])
    first_pose = _pose_centred(model, first_view, sim, camera)
    other_pose = _pose_centred(model, other_view, sim, camera)
    surface = localize_module._surface(model)
    assert surface is not None and surface[1].outline_turns(first_pose)
    shading = _RankedByRotation(surface[1], [(other_pose, 1.0 if wins else 0.5)], 0.8)
    searches = []

    def search_views(feats, templates, seeds, chance, max_candidates, **options):
        searches.append((seeds, max_candidates, options))
        return [ViewCandidate(v, np.asarray(seeds[0]), 100.0, 0.9)
                for v in (first_view, other_view)]

    starts = []

    def refine(edges, camera_, start, contour, options):
        starts.append(start)
        return RefinementResult(start, True, 3, 0.5, 0.9)

    judged = []
    monkeypatch.setattr(localize_module, "search_views", search_views)
    monkeypatch.setattr(localize_module, "refine_pose", refine)
    monkeypatch.setattr(localize_module, "RIVAL_SCALE_FACTORS", ())
    monkeypatch.setattr(localize_module, "_judged",
                        lambda *args: judged.append(args[-1]) or "judged again")
    first = RefinementResult(first_pose, True, 10, 0.5, 0.9)
    fitted = _Fitted(None, location_fit=_LocationFit(loc, first, first_view, sim, first_pose,
                                                     _FitOptions()))
    looked = _wider_look(model, None, None, 1.0, camera, None, None, shading, fitted)

    (seeds, max_candidates, options), = searches
    assert np.array_equal(seeds, [loc.candidates[0].sim])
    assert max_candidates == localize_module.WIDER_VIEW_CANDIDATES
    assert options["screened_views"] == localize_module.WIDER_SCREENED_VIEWS
    # The other view's quick fit first; when it wins, its full fit and then
    # its own outline turns (round two).
    assert rotation_angle_deg(starts[0].R_m2c, other_pose.R_m2c) < 1e-6
    if wins:
        assert looked == "judged again"
        (fit,) = judged
        assert fit.t_view == other_view and fit.location is loc
        assert rotation_angle_deg(fit.result.pose.R_m2c, other_pose.R_m2c) < 1e-6
        assert len(starts) > 2
    else:
        assert looked is fitted and not judged
        assert len(starts) == 1


@pytest.mark.parametrize("outline_views", [True, False])
def test_the_views_of_a_colour_locations_outline_compete_with_its_fit(
        bracket_model, monkeypatch, outline_views):
    # A colour location's view search on the photo found only the first
    # view; its search on the colour's outline found another, the truth's.
    # With that view among the location's colour rivals its fit competes
    # and wins; without, the first view's fit stands. Refinement leaves
    # every pose where it is; the first fit ranks 0.8, the truth 1.0.
    model = bracket_model
    camera, first_view, other_view, sim, loc = _two_views_at_one_location(model)
    rival = loc.candidates[1]
    loc = _Located(loc.match, loc.candidates[:1], (rival,) if outline_views else ())
    other_pose = _pose_centred(model, other_view, sim, camera)
    shading = _RankedByRotation(NearSymmetries(np.zeros((0, 4, 4)), np.ones(0)),
                                [(other_pose, 1.0)], 0.8)
    monkeypatch.setattr(localize_module, "refine_pose", _refine_in_place)
    monkeypatch.setattr(localize_module, "_tilted_refit",
                        lambda edges, camera_, contour, sym, result, fit_options: result)
    monkeypatch.setattr(_FitOptions, "near", classmethod(lambda cls, *args: cls()))
    monkeypatch.setattr(localize_module, "RIVAL_SCALE_FACTORS", ())
    monkeypatch.setattr(localize_module, "_judged", lambda *args: args[-1])
    fit = _final_detection(model, loc, None, 1.0, camera, "edges", "contour", 1.0, shading)
    assert fit.location is loc
    if outline_views:
        assert fit.t_view == other_view
        assert rotation_angle_deg(fit.result.pose.R_m2c, other_pose.R_m2c) < 1e-6
    else:
        assert fit.t_view == first_view


def test_a_near_symmetric_part_gets_more_view_candidates(bracket_model):
    # An egg-like part's outline is nearly the same from several sides: its
    # rival views lie beyond the best few, so the view search returns more.
    blob_model = learn_from_mesh(blob(), LearningConfig(max_level=0, min_level=0,
                                                        contour_level=1))
    assert _view_candidate_count(localize_module._surface(blob_model)) == (
        localize_module.NEAR_SYMMETRIC_VIEW_CANDIDATES)
    assert _view_candidate_count(localize_module._surface(bracket_model)) == (
        localize_module.VIEW_CANDIDATES)
    assert _view_candidate_count(None) == localize_module.VIEW_CANDIDATES
    assert localize_module.NEAR_SYMMETRIC_VIEW_CANDIDATES > localize_module.VIEW_CANDIDATES


@pytest.mark.parametrize("seed", [12, 15, 17])
def test_each_of_three_copies_is_found_once(renderer, bracket_mesh, bracket_model, seed):
    # Three L-brackets in one image, three detections wanted: fits of one
    # copy must not take the places of the others (in these scenes a second
    # fit of one copy did, and a copy went unreported: 88 of 120 copies
    # found in 40 such scenes before, 98 after).
    rng = np.random.default_rng(seed)
    cam = Camera(560.0, 560.0, 319.5, 239.5, 640, 480)
    views = view_directions(1)
    poses = [Pose(Rotation.from_rotvec([0.0, 0.0, rng.uniform(0.0, 2 * np.pi)]).as_matrix()
                  @ views[int(rng.integers(len(views)))].R_m2c,
                  np.array([x, rng.uniform(-60.0, 60.0), rng.uniform(600.0, 750.0)]))
             for x in (-190.0, 0.0, 190.0)]
    image = render_copies(renderer, bracket_mesh, cam, poses)
    dets = localize(bracket_model, image, cam, LocalizeOptions(max_detections=3)).detections
    copies_px = cam.project(np.array([p.t_m2c for p in poses]))
    found = [int(np.argmin(np.hypot(*(copies_px - [d.similarity.x, d.similarity.y]).T)))
             for d in dets
             if np.hypot(*(copies_px - [d.similarity.x, d.similarity.y]).T).min() < 20.0]
    assert sorted(found) == [0, 1, 2]
    assert [d.score for d in dets] == sorted((d.score for d in dets), reverse=True)


def test_larger_images_are_refined_from_coarser_levels() -> None:
    assert _refine_levels(640, 480) == _refine_levels(384, 288) == FINAL_REFINE.levels
    assert _refine_levels(800, 600) == FINAL_REFINE.levels
    assert _refine_levels(1280, 960) == FINAL_REFINE.levels + 1
    assert _refine_levels(1024, 1280) == FINAL_REFINE.levels + 1
    assert _refine_levels(2448, 2048) == FINAL_REFINE.levels + 2
    assert _refine_levels(20_000, 15_000) == 5
    # Options on their own levels or fewer stay as they are.
    assert _on_levels(FINAL_REFINE, FINAL_REFINE.levels) is FINAL_REFINE
    assert _on_levels(QUICK_REFINE, 1) is QUICK_REFINE
    # The extra, coarser levels search and iterate as the coarsest did, and the
    # shift search reaches as far on the new coarsest level.
    deeper = _on_levels(FINAL_REFINE, FINAL_REFINE.levels + 2)
    assert deeper.levels == FINAL_REFINE.levels + 2
    assert deeper.search_px == FINAL_REFINE.search_px + (FINAL_REFINE.search_px[-1],) * 2
    assert deeper.iterations == FINAL_REFINE.iterations + (FINAL_REFINE.iterations[-1],) * 2
    assert deeper.shift_search_px == 4.0 * FINAL_REFINE.shift_search_px
    assert (deeper.polish_px, deeper.min_gradient) == (FINAL_REFINE.polish_px,
                                                       FINAL_REFINE.min_gradient)


def test_a_start_as_far_off_as_at_640_px_is_captured_in_a_1280_px_image(
        bracket_contour_scene) -> None:
    # The start the search level gives is off by as many pixels of a
    # 640-px image whatever the camera's resolution, so by twice as many in
    # a 1280-px one: 28 px sideways, 4 degrees and 2 % of depth here. The
    # two levels set for 640 px (a 16-px shift search on the 640-px level)
    # do not capture it; a third level to start on does.
    renderer, prepared, contour = bracket_contour_scene
    cam = Camera(1200.0, 1200.0, 645.5, 475.5, 1280, 960)
    rng = np.random.default_rng(0)
    truth = Pose(Rotation.random(random_state=0).as_matrix(), np.array([20.0, -15.0, 600.0]))
    image = renderer.render(prepared, cam, truth).color
    axis = rng.normal(size=3)
    turn = Rotation.from_rotvec(axis / np.linalg.norm(axis) * np.radians(4.0)).as_matrix()
    start = Pose(turn @ truth.R_m2c, truth.t_m2c * [1.0, 1.0, 1.02] + [14.0 * 0.6, 14.0 * 0.8, 0])
    edges = prepare_edges(image, _refine_levels(cam.width, cam.height))

    def error(options: RefineOptions) -> tuple[float, float]:
        pose = refine_pose(edges, cam, start, contour, options).pose
        return (rotation_angle_deg(pose.R_m2c, truth.R_m2c),
                float(np.linalg.norm(pose.t_m2c - truth.t_m2c)))

    rot_deg, t_mm = error(_on_levels(FINAL_REFINE, edges.levels))
    assert rot_deg < 1.0 and t_mm < 3.0
    rot_deg, t_mm = error(FINAL_REFINE)
    assert rot_deg > 2.0 or t_mm > 6.0


def test_fits_stuck_after_far_starts_are_freed_by_their_tilted_restarts(
        bracket_contour_scene) -> None:
    # Twelve poses of the ribbed bracket, each refined from a start turned
    # 14° out of the image plane (and 2 % too far): beyond the refinement's
    # capture range in rotation for some. The tilted restarts free two of
    # the stuck fits and never replace a fit but by a clearly better one.
    renderer, prepared, contour = bracket_contour_scene
    cam = Camera(600.0, 600.0, 319.5, 239.5, 640, 480)
    no_symmetry = Symmetries(np.eye(4)[None])
    right_plain = right_tilted = 0
    for seed in range(12):
        rng = np.random.default_rng(seed)
        truth = Pose(Rotation.random(random_state=seed).as_matrix(), np.array([10.0, -5.0, 500.0]))
        image = renderer.render(prepared, cam, truth, lights=TABLE_LIGHTS,
                                background_rgb=(90, 90, 90)).color
        edges = prepare_edges(image, 2)
        options = _FitOptions.near(edges, cam, truth, diameter_mm=127.4)  # the bracket's
        axis = rng.normal(size=2)
        axis /= np.linalg.norm(axis)
        turn = Rotation.from_rotvec(np.radians(14.0) * np.array([axis[0], axis[1], 0.0]))
        start = Pose(turn.as_matrix() @ truth.R_m2c, truth.t_m2c * [1.0, 1.0, 1.02])
        plain = refine_pose(edges, cam, start, contour, options.final)
        tilted = _tilted_refit(edges, cam, contour, no_symmetry, plain, options)
        assert tilted is plain or tilted.inlier_fraction >= plain.inlier_fraction + TILT_MIN_GAIN
        right_plain += rotation_angle_deg(plain.pose.R_m2c, truth.R_m2c) < 1.0
        right_tilted += rotation_angle_deg(tilted.pose.R_m2c, truth.R_m2c) < 1.0
    assert right_tilted >= right_plain + 2


def test_parts_localized_in_one_prepared_scene_get_their_own_answers(
        renderer, bracket_model, orange_model, monkeypatch):
    # A request for several parts finds the image's features and builds
    # its edge pyramid once; each part's detections are those it gets alone.
    camera = Camera(600.0, 600.0, 319.5, 239.5, 640, 480)
    truth = Pose(Rotation.from_euler("xyz", [0.5, -0.4, 0.9]).as_matrix(),
                 np.array([10.0, -5.0, 420.0]))
    image = render_scene(renderer, coloured_bracket(ORANGE), camera, truth, clutter=6)
    alone = {id(m): localize(m, image, camera).detections for m in (bracket_model, orange_model)}
    assert all(alone.values())
    extracted = []
    extract = localize_module.extract_features

    def spied_extract(level, **options):
        # The image's features; the colour outline's edges are each part's.
        if not options.get("edges_only"):
            extracted.append(level)
        return extract(level, **options)

    monkeypatch.setattr(localize_module, "extract_features", spied_extract)
    built = []
    edges = localize_module.prepare_edges
    monkeypatch.setattr(localize_module, "prepare_edges",
                        lambda *args: built.append(args) or edges(*args))
    for start_edges in (True, False):  # False: the pyramid is built when a fit needs it
        extracted.clear()
        built.clear()
        scene = prepare_scene(image, camera, edges=start_edges)
        for model in (orange_model, bracket_model):
            result = localize_in_scene(model, scene)
            assert result.timing_ms["features"] == scene.features_ms
            expected = alone[id(model)]
            assert len(result.detections) == len(expected)
            for got, want in zip(result.detections, expected, strict=True):
                assert got.score == want.score
                assert np.array_equal(got.pose.R_m2c, want.pose.R_m2c)
                assert np.array_equal(got.pose.t_m2c, want.pose.t_m2c)
        scene.release()
        # Once on the level, and once on the image itself if a part's
        # search settled nothing on the level (localize_in_scene).
        assert [a.shape[:2] for a in extracted] in ([(300, 400)], [(300, 400), (480, 640)])
        assert len(built) == 1


def _refined_fit(tag: int, chance_corrected: float, settled: bool) -> _Fitted:
    """A refined fit, settled or confirmed short of it (see _settled)."""
    score = 0.95 if settled else GOOD_FIT_FRACTION - 0.05
    return _fit(score, True, tag, chance_corrected=chance_corrected)


def test_a_search_that_settles_nothing_on_its_level_is_repeated_on_a_finer_one(
        monkeypatch) -> None:
    # The answer of the level (factor 0.625 for 640x480) stands when its
    # best fit settles; otherwise the image itself is searched too, and its
    # answer replaces the level's when its best fit settles and ranks higher.
    camera = Camera(600.0, 600.0, 319.5, 239.5, 640, 480)
    image = np.random.default_rng(3).integers(0, 255, (480, 640), dtype=np.uint8)
    scene = prepare_scene(image, camera, edges=False)
    assert scene.factor < 1.0
    searched: list[float] = []

    def run(answers, options=None, in_colour=False, deadline=None):
        def on_level(model, on_scene, opts, budget):
            searched.append(on_scene.factor)
            best = answers[len(searched) - 1]
            return _LevelAnswer([] if best is None else [best.detection], best, in_colour, {})
        searched.clear()
        monkeypatch.setattr(localize_module, "_localize_on_level", on_level)
        monkeypatch.setattr(localize_module, "refines", lambda model, opts: opts.refine)
        return localize_in_scene(None, scene, options or LocalizeOptions(), deadline=deadline)

    settled, settled_better = _refined_fit(0, 0.9, True), _refined_fit(1, 0.95, True)
    assert _settled(settled) and _settled(settled_better)
    result = run([settled, settled_better])
    assert searched == [scene.factor] and result.detections == [settled.detection]
    assert "finer_search" not in result.timing_ms
    doubtful, doubtful_better = _refined_fit(2, 0.7, False), _refined_fit(3, 0.8, False)
    assert not _settled(doubtful) and not _settled(doubtful_better)
    result = run([doubtful, settled])
    assert searched == [scene.factor, 1.0] and result.detections == [settled.detection]
    assert result.timing_ms["finer_search"] > 0.0
    # The finer search's fit must settle to overrule, and rank higher.
    assert run([doubtful, doubtful_better]).detections == [doubtful.detection]
    assert run([None, doubtful]).detections == []
    assert run([None, settled]).detections == [settled.detection]
    assert run([doubtful, None]).detections == [doubtful.detection]
    confirmed_short = _refined_fit(4, 0.97, False)
    assert run([confirmed_short, settled]).detections == [confirmed_short.detection]
    # A fit that confirms FINER_SEARCH_NEEDLESS_FRACTION of its contour both
    # plainly and beyond chance has resolved the outline on this level, settled
    # or not (its inside looks like its surroundings): searched once.
    bar = FINER_SEARCH_NEEDLESS_FRACTION
    resolved = replace(_fit(bar, True, 5, chance_corrected=bar),
                       figure_ground=FIRST_FIT_MIN_FIGURE_GROUND - 0.01)
    assert not _settled(resolved) and _resolved(resolved)
    assert run([resolved, settled_better]).detections == [resolved.detection]
    assert searched == [scene.factor]
    for short in (replace(resolved, chance_corrected=bar - 0.01),
                  replace(resolved, detection=replace(resolved.detection, score=bar - 0.01)),
                  replace(resolved, detection=replace(resolved.detection, refined=False))):
        assert not _resolved(short)
        run([short, settled])
        assert searched == [scene.factor, 1.0]
    # Not once the time budget is spent: the level's answer stands, and the
    # result says the search was cut short (it was not, when it had time).
    result = run([doubtful, settled], deadline=time.perf_counter() - 1.0)
    assert searched == [scene.factor] and result.detections == [doubtful.detection]
    assert result.timed_out and "finer_search" not in result.timing_ms
    assert not run([doubtful, settled], LocalizeOptions(timeout_ms=1e7)).timed_out
    assert searched == [scene.factor, 1.0]
    # Nor when what is left of it is less than the finer search is expected
    # to take: the level's time, features included, times the ratio of the
    # levels' pixels (here 40 ms of features alone, times 2.56).
    scene.features_ms = 40.0
    assert _finer_search_expected_s(scene, 0.0) == pytest.approx(0.04 * (640 / 400) ** 2)
    result = run([doubtful, settled], deadline=time.perf_counter() + 0.05)
    assert searched == [scene.factor] and result.timed_out
    assert not run([doubtful, settled], deadline=time.perf_counter() + 10.0).timed_out
    assert searched == [scene.factor, 1.0]
    # A budget spent with nothing left to start cuts nothing short.
    result = run([settled, settled_better], deadline=time.perf_counter() - 1.0)
    assert not result.timed_out and result.detections == [settled.detection]
    # In colour, fits rank by the colour and not by settling: searched once.
    assert run([doubtful, settled], in_colour=True).detections == [doubtful.detection]
    assert searched == [scene.factor]
    # Without refinement nothing settles and nothing is searched again.
    run([doubtful, settled], LocalizeOptions(refine=False))
    assert searched == [scene.factor]
    # An image no larger than the level is searched once.
    small = Camera(300.0, 300.0, 191.5, 143.5, 384, 288)
    scene = prepare_scene(image[:288, :384], small, edges=False)
    assert scene.factor == 1.0 and scene.at_finer_level() is scene
    run([doubtful, settled])
    assert searched == [1.0]


@pytest.mark.parametrize("timeout_ms", [0.0, -5.0, math.nan, math.inf])
def test_a_time_budget_must_be_a_positive_number_of_ms(timeout_ms) -> None:
    with pytest.raises(InvalidInputError, match="positive number of milliseconds") as err:
        LocalizeOptions(timeout_ms=timeout_ms)
    assert err.value.field == "options.timeout_ms"


def test_a_spent_time_budget_starts_no_further_search(bracket_model, renderer,
                                                      monkeypatch) -> None:
    # Boxes without the bracket, 640x480: places to fit but nothing settles,
    # so without a budget the spare locations and the finer level are
    # searched too; with a spent one neither is (one fit, the first
    # location's), and the result says so. A budget that lasts changes nothing.
    camera = Camera(600.0, 600.0, 319.5, 239.5, 640, 480)
    gen = np.random.default_rng(0)
    boxes = []
    for _ in range(14):
        box = trimesh.creation.box(gen.uniform([15, 10, 10], [120, 30, 30]))
        R = trimesh.transformations.random_rotation_matrix(gen.random(3))[:3, :3]
        u, v = gen.uniform([0, 0], [camera.width, camera.height])
        z = gen.uniform(500, 900)
        boxes.append((prepare(box), Pose(R, z * np.array([(u - camera.cx) / camera.fx,
                                                            (v - camera.cy) / camera.fy, 1]))))
    image = renderer.render_scene(boxes, camera, lights=TABLE_LIGHTS,
                                  background_rgb=(40, 40, 40)).color
    fitted: list[object] = []
    final_detection = localize_module._final_detection
    monkeypatch.setattr(localize_module, "_final_detection",
                        lambda *args: fitted.append(args[1]) or final_detection(*args))
    free = localize(bracket_model, image, camera, LocalizeOptions(min_score=0.0))
    assert "finer_search" in free.timing_ms and not free.timed_out
    fits_free = len(fitted)
    assert fits_free > 2  # the first location and its spares, on both levels
    lasting = localize(bracket_model, image, camera,
                       LocalizeOptions(min_score=0.0, timeout_ms=1e7))
    assert not lasting.timed_out and len(fitted) == 2 * fits_free
    assert [d.pose.t_m2c.tolist() for d in lasting.detections] == \
        [d.pose.t_m2c.tolist() for d in free.detections]
    fitted.clear()
    spent = localize(bracket_model, image, camera,
                     LocalizeOptions(min_score=0.0, timeout_ms=1e-3))
    assert spent.timed_out and "finer_search" not in spent.timing_ms
    assert len(fitted) == 1


def test_the_finer_level_finds_its_features_once_and_shares_the_pyramid(monkeypatch) -> None:
    camera = Camera(600.0, 600.0, 319.5, 239.5, 640, 480)
    image = np.random.default_rng(4).integers(0, 255, (480, 640, 3), dtype=np.uint8)
    built = []
    edges = localize_module.prepare_edges
    monkeypatch.setattr(localize_module, "prepare_edges",
                        lambda *args: built.append(args) or edges(*args))
    scene = prepare_scene(image, camera)
    assert scene.has_finer_level()
    finer = scene.at_finer_level()
    assert finer is scene.at_finer_level() and not finer.has_finer_level()
    # Up to 640x480 the finer level is the image itself.
    assert finer.factor == 1.0 and finer.level is scene.image and finer.camera is scene.camera
    assert finer.features.edge_distance.shape == (480, 640)
    assert scene.features.edge_distance.shape == (300, 400)
    assert finer.edges() is scene.edges()
    assert len(built) == 1
    scene.release()


@pytest.mark.parametrize(("width", "height", "finer_shape"),
                         [(1280, 960, (480, 640)), (500, 400, (400, 500)), (384, 288, None)])
def test_larger_images_are_searched_again_on_a_level_of_640_px(width, height,
                                                                finer_shape) -> None:
    camera = Camera(600.0, 600.0, (width - 1) / 2, (height - 1) / 2, width, height)
    image = np.random.default_rng(5).integers(0, 255, (height, width), dtype=np.uint8)
    scene = prepare_scene(image, camera, edges=False)
    assert scene.has_finer_level() == (finer_shape is not None)
    finer = scene.at_finer_level()
    if finer_shape is None:
        assert finer is scene
    else:
        assert finer.level.shape == finer_shape
        assert finer.factor == pytest.approx(finer_shape[1] / width)


def test_refined_fits_of_two_searches_compare_without_their_evidence() -> None:
    # The view search's evidence is measured on each level's own edges: two
    # searches' best fits compare by what their refinements confirmed.
    weak_evidence = _fit(0.9, True, 0, chance_corrected=0.85, evidence=10.0)
    strong_evidence = _fit(0.9, True, 1, chance_corrected=0.8, evidence=1000.0)
    assert _answer_rank(weak_evidence) > _answer_rank(strong_evidence)
    standing_out = replace(strong_evidence, figure_ground=FIGURE_GROUND_FULL)
    assert _answer_rank(standing_out) == pytest.approx(0.8 + FIGURE_GROUND_WEIGHT)
    assert _answer_rank(_fit(0.99, False, 2)) < _answer_rank(_fit(0.5, True, 3, 0.1))
