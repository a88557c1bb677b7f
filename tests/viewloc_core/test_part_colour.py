"""The part's colour: histogram, back-projection, proposals, centroid, agreement;
learning keeps it only for coloured parts; localization uses it to pick the
part among look-alikes of other colours."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import trimesh

from tests.viewloc_core.conftest import ORANGE, coloured_bracket
from viewloc_core import part_colour as pc
from viewloc_core.camera import Camera
from viewloc_core.errors import ModelFormatError
from viewloc_core.localize import LocalizeOptions, localize
from viewloc_core.model import model_from_arrays, model_to_arrays
from viewloc_core.pose import Pose
from viewloc_core.render import Light, prepare

BLUE = (30, 70, 200)

#: The camera and the grey table of the scenes of coloured brackets.
_CAMERA = Camera(600.0, 600.0, 319.5, 239.5, 640, 480)


def _on_grey_table(renderer, parts: list[tuple[trimesh.Trimesh, Pose]]) -> np.ndarray:
    """(H, W, 3) uint8: the meshes at their poses on a mid-grey table, lit
    from the upper right, seen by :data:`_CAMERA`."""
    lights = [Light("directional", direction_cam=(0.6, 0.5, 1.0), intensity=3.0),
              Light("ambient", intensity=0.3)]
    return renderer.render_scene([(prepare(mesh), pose) for mesh, pose in parts], _CAMERA,
                                 lights=lights, background_rgb=(90, 90, 90)).color


def _scene_with_patch(colour: tuple[int, int, int], xy: tuple[int, int], half: int,
                      seed: int = 0) -> np.ndarray:
    """A 300x400 scene of grey-ish noise with a square patch of ``colour``."""
    gen = np.random.default_rng(seed)
    img = gen.integers(60, 200, (300, 400, 1)).repeat(3, axis=2).astype(np.int32)
    img += gen.integers(-10, 10, img.shape)
    x, y = xy
    img[y - half:y + half + 1, x - half:x + half + 1] = colour
    return np.clip(img, 0, 255).astype(np.uint8)


def _histogram_of(colour: tuple[int, int, int]) -> np.ndarray:
    acc = pc.ColourAccumulator(seed=0)
    view = np.zeros((64, 64, 3), np.uint8)
    mask = np.zeros((64, 64), np.uint8)
    for shade in (0.6, 0.8, 1.0):  # lit and shaded faces: same chromaticity
        view[:] = np.clip(np.array(colour) * shade, 0, 255).astype(np.uint8)
        mask[8:56, 8:56] = 1
        acc.add(view, mask)
    hist = acc.histogram()
    assert hist is not None
    return hist


def test_the_histogram_holds_the_parts_chromaticity_whatever_its_brightness() -> None:
    hist = _histogram_of(ORANGE)
    assert hist.shape == (pc.N_BINS,)
    assert hist.sum() == pytest.approx(1.0, abs=1e-5)
    orange_bin = pc.colour_bins(np.array([ORANGE], np.uint8))[0]
    dimmer_bin = pc.colour_bins((np.array([ORANGE]) * 0.5).astype(np.uint8))[0]
    blue_bin = pc.colour_bins(np.array([BLUE], np.uint8))[0]
    assert orange_bin == dimmer_bin
    assert hist[orange_bin] > 20 * hist[blue_bin]


def test_no_histogram_from_grey_images_or_too_few_pixels() -> None:
    acc = pc.ColourAccumulator()
    acc.add(np.full((32, 32), 128, np.uint8), np.ones((32, 32)))
    assert acc.histogram() is None
    acc.add(np.full((32, 32, 3), 128, np.uint8), np.zeros((32, 32)))
    assert acc.histogram() is None
    with pytest.raises(Exception, match="mask size"):
        acc.add(np.zeros((32, 32, 3), np.uint8), np.ones((16, 16)))


def test_views_that_disagree_about_the_parts_colour_give_no_histogram() -> None:
    """A part photographed in a new colour each time has no colour of its own;
    a two-tone part seen from all sides (both tones in most views) keeps one."""
    gen = np.random.default_rng(3)
    view = np.zeros((48, 48, 3), np.uint8)
    mask = np.zeros((48, 48), np.uint8)
    mask[4:44, 4:44] = 1
    one_colour, many_colours, two_tone = (pc.ColourAccumulator(seed=0) for _ in range(3))
    for _ in range(30):
        shade = gen.uniform(0.5, 1.0)  # lights move brightness, not chromaticity
        view[:] = (np.array(ORANGE) * shade).astype(np.uint8)
        one_colour.add(view, mask)
        view[:] = gen.integers(50, 255, 3).astype(np.uint8)
        many_colours.add(view, mask)
        # Orange and blue, the share of each changing with the side seen.
        split = int(gen.integers(16, 33))
        view[:, :split] = (np.array(ORANGE) * shade).astype(np.uint8)
        view[:, split:] = (np.array(BLUE) * shade).astype(np.uint8)
        two_tone.add(view, mask)
    assert one_colour.view_agreement() > 0.95 and one_colour.histogram() is not None
    assert two_tone.view_agreement() > pc.MIN_VIEW_AGREEMENT
    assert two_tone.histogram() is not None
    assert many_colours.view_agreement() < pc.MIN_VIEW_AGREEMENT
    assert many_colours.histogram() is None
    assert pc.ColourAccumulator().view_agreement() == 0.0


def test_a_colour_image_without_colours_is_told_from_one_with_them() -> None:
    grey = np.random.default_rng(0).integers(0, 256, (48, 64), dtype=np.uint8)
    as_rgb = np.repeat(grey[:, :, None], 3, axis=2)
    assert pc.is_grey_in_colour(as_rgb)
    assert pc.is_grey_in_colour(np.dstack([as_rgb, np.full_like(grey, 255)]))  # RGBA
    assert pc.is_grey_in_colour(as_rgb.astype(np.uint16) * 257)
    # Channels a few levels apart (a compressed monochrome frame) are still grey.
    noisy = np.clip(as_rgb.astype(np.int16) + np.random.default_rng(1).integers(
        -3, 4, as_rgb.shape), 0, 255).astype(np.uint8)
    assert pc.is_grey_in_colour(noisy)
    # Not grey in colour: a plain grey image, one with a coloured patch, floats.
    assert not pc.is_grey_in_colour(grey)
    assert not pc.is_grey_in_colour(_scene_with_patch(ORANGE, (200, 150), 12))
    assert not pc.is_grey_in_colour(as_rgb.astype(np.float32) / 255.0)


def test_a_small_coloured_part_on_a_neutral_background_is_colour() -> None:
    # A 640x480 frame of a neutral conveyor with sensor noise (channels a few
    # levels apart) and a small orange part, 0.3 % of the frame: a colour
    # camera's image, whose only colour is the part's.
    gen = np.random.default_rng(2)
    belt = np.repeat(gen.integers(90, 140, (480, 640, 1)), 3, axis=2)
    frame = np.clip(belt + gen.integers(-3, 4, belt.shape), 0, 255).astype(np.uint8)
    assert pc.is_grey_in_colour(frame)
    frame[200:230, 300:330] = ORANGE
    assert not pc.is_grey_in_colour(frame)


def test_back_projection_is_positive_on_the_part_and_negative_around_it() -> None:
    hist = _histogram_of(ORANGE)
    img = _scene_with_patch(ORANGE, (250, 120), 12)
    ratio = pc.log_ratio_map(img, hist)
    assert ratio is not None and ratio.shape == img.shape[:2]
    assert ratio[120, 250] > 1.0
    assert np.median(ratio[:, :150]) < 0.0
    assert pc.log_ratio_map(img[..., 0], hist) is None
    # A grey image stored as RGB carries no colour either.
    assert pc.log_ratio_map(img[..., :1].repeat(3, axis=2), hist) is None
    assert pc.log_ratio_map(img.astype(np.uint16) * 257, hist) == pytest.approx(ratio)


def test_the_posterior_map_reads_each_pixel_by_its_colour_bin() -> None:
    """The posterior of a full-resolution image from the bins' posteriors a
    level of the same scene gave: each pixel its bin's value, as the
    per-pixel posterior of the log ratio map."""
    from viewloc_core.errors import InvalidInputError

    hist = _histogram_of(ORANGE)
    img = _scene_with_patch(ORANGE, (250, 120), 12)
    binned = pc.bin_log_ratios(img, hist)
    assert binned is not None
    table = pc.posterior(binned[1])
    full = pc.posterior_map(img, table)
    ratio = pc.log_ratio_map(img, hist)
    assert full is not None and ratio is not None and full.shape == img.shape[:2]
    assert full == pytest.approx(pc.posterior(ratio))
    assert full[120, 250] > 0.7 and np.median(full[:, :150]) < 0.5
    assert pc.posterior_map(img.astype(np.uint16) * 257, table) == pytest.approx(full)
    # An RGBA frame's colour channels are a strided view: the same values.
    rgba = np.dstack([img, np.full(img.shape[:2], 255, np.uint8)])
    assert np.array_equal(pc.posterior_map(rgba, table), full)
    assert pc.posterior_map(img[..., 0], table) is None
    assert pc.posterior_map(img.astype(np.float32), table) is None
    with pytest.raises(InvalidInputError):
        pc.posterior_map(img, table[:-1])


def test_the_expected_agreement_is_high_for_a_rare_colour_and_low_for_a_common_one() -> None:
    # What the part itself would score depends on the scene: a small orange
    # patch among grey is nearly certain to be the part, a scene half
    # orange makes orange no evidence either way.
    hist = _histogram_of(ORANGE)
    rare = pc.bin_log_ratios(_scene_with_patch(ORANGE, (250, 120), 12), hist)
    common = _scene_with_patch(ORANGE, (250, 120), 12)
    common[:, :200] = ORANGE
    common_ratios = pc.bin_log_ratios(common, hist)
    assert rare is not None and common_ratios is not None
    e_rare = pc.expected_agreement(hist, rare[1])
    e_common = pc.expected_agreement(hist, common_ratios[1])
    assert e_rare > 0.9
    assert 0.3 < e_common < 0.7
    # It is what the part's own pixels get, on average.
    post = pc.posterior(rare[1][rare[0]])
    assert float(post[110:131, 240:261].mean()) == pytest.approx(e_rare, abs=0.05)


def test_the_best_window_is_the_part_with_about_its_size() -> None:
    hist = _histogram_of(ORANGE)
    img = _scene_with_patch(ORANGE, (250, 120), 16)
    img[200:211, 50:61] = ORANGE  # a smaller patch of the same colour
    ratio = pc.log_ratio_map(img, hist)
    assert ratio is not None
    props = pc.propose(ratio, np.geomspace(2.0, 40.0, 16), 3)
    assert 1 <= len(props) <= 3
    best = props[0]
    assert abs(best.x - 250) <= 3 and abs(best.y - 120) <= 3
    assert 8.0 <= best.half_size_px <= 24.0
    assert any(abs(p.x - 55) <= 4 and abs(p.y - 205) <= 4 for p in props[1:])
    strengths = [p.strength for p in props]
    assert strengths == sorted(strengths, reverse=True)


def test_a_region_of_the_parts_colour_larger_than_the_part_takes_one_proposal_apart() -> None:
    # A patch of the part's colour twice the part's size (half side 20 px),
    # and the part (half side 10 px) elsewhere; windows of half sides 2-12
    # px. Kept outside the window alone, every proposal lands on the large
    # patch; kept two half sides apart (a part's radius when the window is
    # a quarter of its diameter), the second is the part.
    hist = _histogram_of(ORANGE)
    img = _scene_with_patch(ORANGE, (100, 150), 20)
    img[195:216, 300:321] = ORANGE
    ratio = pc.log_ratio_map(img, hist)
    assert ratio is not None
    halves = np.geomspace(2.0, 12.0, 16)

    def on_part(p: pc.ColourProposal) -> bool:
        return abs(p.x - 310) <= 4 and abs(p.y - 205) <= 4

    near = pc.propose(ratio, halves, 3)
    assert len(near) == 3 and not any(on_part(p) for p in near)
    assert all(abs(p.x - 100) <= 20 and abs(p.y - 150) <= 20 for p in near)
    apart = pc.propose(ratio, halves, 3, exclusion_halves=2.0)
    assert abs(apart[0].x - near[0].x) <= 1 and abs(apart[0].y - near[0].y) <= 1
    assert on_part(apart[1])


def test_the_centroid_moves_to_the_middle_of_the_parts_colours() -> None:
    hist = _histogram_of(ORANGE)
    img = _scene_with_patch(ORANGE, (200, 150), 20)
    ratio = pc.log_ratio_map(img, hist)
    assert ratio is not None
    x0, y0 = 193.0, 144.0
    x, y = pc.centroid(ratio, x0, y0, 22.0)
    assert np.hypot(x - 200, y - 150) < 0.5 * np.hypot(x0 - 200, y0 - 150)
    assert abs(x - 200) < 2.0 and abs(y - 150) < 2.0
    # Nothing part-like around: the start is kept.
    assert pc.centroid(np.full((50, 50), -1.0, np.float32), 10.0, 20.0, 5.0) == (10.0, 20.0)


def test_agreement_is_the_mean_posterior_under_the_points() -> None:
    post = np.zeros((10, 10), np.float32)
    post[:, 5:] = 1.0
    assert pc.agreement(post, np.array([[6.0, 2.0], [7.0, 3.0]])) == pytest.approx(1.0)
    assert pc.agreement(post, np.array([[1.0, 2.0], [7.0, 3.0], [50.0, 3.0]])) == (
        pytest.approx(0.5))
    assert pc.agreement(post, np.array([[-5.0, 2.0]])) is None
    assert np.all((pc.posterior(np.array([-2.0, 0.0, 3.0], np.float32)) > 0)
                  & (pc.posterior(np.array([-2.0, 0.0, 3.0], np.float32)) < 1))


def test_learning_keeps_the_colours_of_a_coloured_mesh_only(orange_model, bracket_model):
    assert bracket_model.colour_histogram is None
    hist = orange_model.colour_histogram
    assert hist is not None
    assert hist[pc.colour_bins(np.array([ORANGE], np.uint8))[0]] > 0.05
    arrays, meta = model_to_arrays(orange_model)
    back = model_from_arrays(arrays, meta)
    assert back.colour_histogram is not None
    assert np.array_equal(back.colour_histogram, hist)
    arrays["colour_histogram"] = hist[:10]
    with pytest.raises(ModelFormatError):
        model_from_arrays(arrays, meta)


def test_learning_keeps_the_vertex_colours_of_a_coloured_mesh_only(orange_model, bracket_model):
    assert bracket_model.mesh_vertex_colours is None
    assert "mesh_vertex_colours" not in model_to_arrays(bracket_model)[0]
    colours = orange_model.mesh_vertex_colours
    assert colours is not None and orange_model.mesh_vertices_mm is not None
    assert colours.shape == (len(orange_model.mesh_vertices_mm), 3)
    assert np.all(colours == ORANGE)
    arrays, meta = model_to_arrays(orange_model)
    back = model_from_arrays(arrays, meta)
    assert back.mesh_vertex_colours is not None
    assert np.array_equal(back.mesh_vertex_colours, colours)
    for broken in (colours[:-1], colours.astype(np.float32), colours[:, :2]):
        arrays["mesh_vertex_colours"] = broken
        with pytest.raises(ModelFormatError):
            model_from_arrays(arrays, meta)


def test_only_a_patterned_parts_surface_samples_carry_its_albedo(orange_model):
    """The localizer's surface samples of a part of one colour (the orange
    bracket) carry no albedo, so its shading cue is the plain one; those of
    the same mesh painted half dark do."""
    from viewloc_core.localize import _surface

    surface = _surface(orange_model)
    assert surface is not None and surface[0].albedo is None
    vertices = orange_model.mesh_vertices_mm
    colours = np.array(orange_model.mesh_vertex_colours)
    colours[vertices[:, 0] < np.median(vertices[:, 0])] = (40, 40, 40)
    painted = _surface(replace(orange_model, mesh_vertex_colours=colours))
    assert painted is not None and painted[0].albedo is not None
    x = painted[0].points_mm[:, 0] + orange_model.origin_offset_mm[0]
    dark = painted[0].albedo < 0.3
    assert np.mean(x[dark]) < np.mean(x[~dark])


def test_the_part_is_told_from_a_look_alike_of_another_colour(orange_model, renderer):
    """An orange and a blue bracket of the same shape: the orange part's
    model reports the orange one, and its pose. Without its colours the
    same model reports the blue one (its outline is seen more clearly), so
    the colour decides."""
    camera = _CAMERA
    R = trimesh.transformations.euler_matrix(0.5, -0.4, 0.9)[:3, :3]
    R_blue = trimesh.transformations.euler_matrix(-0.6, 0.5, 2.4)[:3, :3]
    orange_pose = Pose(R_blue, np.array([-100.0, -20.0, 500.0]))
    blue_pose = Pose(R, np.array([90.0, 30.0, 560.0]))
    image = _on_grey_table(renderer, [(coloured_bracket(ORANGE), orange_pose),
                                      (coloured_bracket(BLUE), blue_pose)])
    dets = localize(orange_model, image, camera).detections
    assert dets
    t = dets[0].pose.t_m2c
    assert np.linalg.norm(t - orange_pose.t_m2c) < 15.0, t
    without_colour = localize(replace(orange_model, colour_histogram=None), image,
                              camera).detections
    assert without_colour
    assert np.linalg.norm(without_colour[0].pose.t_m2c - blue_pose.t_m2c) < 15.0
    # The scene from a monochrome camera, stored as RGB: the colour cue is
    # off, and the answer is that of the model without colours (the colour
    # gate does not drop fits for want of colour).
    grey = np.repeat(image.mean(axis=2, keepdims=True), 3, axis=2).astype(np.uint8)
    anything = LocalizeOptions(min_score=0.0)
    with_hist = localize(orange_model, grey, camera, anything).detections
    without_hist = localize(replace(orange_model, colour_histogram=None), grey, camera,
                            anything).detections
    assert with_hist and [d.pose.t_m2c.tolist() for d in with_hist] == [
        d.pose.t_m2c.tolist() for d in without_hist]


def _orange_disc_in_grey_clutter() -> np.ndarray:
    """(300, 400, 3) uint8: an orange disc of radius 40 px at (200, 150) in
    dense grey clutter (edges of every orientation)."""
    gen = np.random.default_rng(0)
    image = np.full((300, 400, 3), 120, np.uint8)
    for _ in range(900):
        x, y = gen.integers(0, [400, 300])
        w, h = gen.integers(4, 30, 2)
        image[y:y + h, x:x + w] = gen.integers(40, 220)
    yy, xx = np.mgrid[:300, :400]
    image[(xx - 200) ** 2 + (yy - 150) ** 2 < 40 ** 2] = ORANGE
    return image


def test_a_colour_location_explained_no_better_than_clutter_is_not_fitted(
        orange_model, monkeypatch):
    """An orange disc in grey clutter draws the colour proposals; where the
    part's colours are common in the scene (here its own colours' agreement
    set to 0.6: rarity 0.2, under COLOUR_OUTLINE_MIN_RARITY) whether it is
    handed on to be fitted depends on the evidence of its best view on the
    photo's edges alone (COLOUR_MIN_EVIDENCE): here the views' likelihood
    ratios are shifted to put the best one just under and just over the
    bar."""
    import viewloc_core.localize as localize_module
    from viewloc_core.align import AlignConfig
    from viewloc_core.edge_evidence import chance_rates
    from viewloc_core.features import extract_features
    from viewloc_core.view_search import view_templates

    image = _orange_disc_in_grey_clutter()
    rare_colour = localize_module._ColourScene.of(orange_model, image, 1.0)
    assert rare_colour is not None
    colour = replace(rare_colour, expected_agreement=0.6)
    assert localize_module._rarity(colour.expected_agreement) < (
        localize_module.COLOUR_OUTLINE_MIN_RARITY)
    feats = extract_features(image)
    search = localize_module.search_views

    best_views: list[float] = []  # each proposal's best view's own evidence

    def located(shift: float) -> list:
        def shifted(feats_, *args, **kwargs):
            found = search(feats_, *args, **kwargs)
            if feats_ is feats:  # the photo's, not the colour outline's search
                best_views.extend(c.log_likelihood_ratio for c in found[:1])
            return [replace(c, log_likelihood_ratio=c.log_likelihood_ratio + shift)
                    for c in found]

        with monkeypatch.context() as patch:
            patch.setattr(localize_module, "search_views", shifted)
            return localize_module._colour_locations(
                orange_model, colour, feats, view_templates(orange_model),
                chance_rates(feats), AlignConfig(), [])

    # Every proposal's best view lifted far over the bar: the proposals are
    # at the disc, and the best evidence is the disc's (a disc is no
    # bracket: its outline explains little).
    near = [loc for loc in located(1e4)
            if np.hypot(*(loc.candidates[0].sim[:2] - [200.0, 150.0])) < 40]
    assert near
    best = max(best_views)
    bar = localize_module.COLOUR_MIN_EVIDENCE
    assert not [loc for loc in located(bar - best)
                if np.hypot(*(loc.candidates[0].sim[:2] - [200.0, 150.0])) < 40]
    assert [loc for loc in located(bar - best + 1.0)
            if np.hypot(*(loc.candidates[0].sim[:2] - [200.0, 150.0])) < 40]


def test_a_colour_location_of_rare_colours_without_edges_is_searched_on_its_outline(
        orange_model, monkeypatch):
    """Where the part's colours are rare in the scene (the orange disc in
    grey clutter: agreement about 1) and the photo's edges at a colour
    location explain no view (its views' evidence shifted under
    COLOUR_MIN_EVIDENCE), the location is searched on the outline of the
    part's colour from the same seeds and kept with those views, without
    rivals; when the outline explains none either (shifted under the bar
    too), it is not fitted."""
    import viewloc_core.localize as localize_module
    from viewloc_core.align import AlignConfig
    from viewloc_core.edge_evidence import chance_rates
    from viewloc_core.features import extract_features
    from viewloc_core.view_search import view_templates

    image = _orange_disc_in_grey_clutter()
    colour = localize_module._ColourScene.of(orange_model, image, 1.0)
    assert colour is not None
    assert localize_module._rarity(colour.expected_agreement) >= (
        localize_module.COLOUR_OUTLINE_MIN_RARITY)
    feats = extract_features(image)
    search = localize_module.search_views
    bar = localize_module.COLOUR_MIN_EVIDENCE

    def located(outline_shift: float) -> tuple[list, list]:
        searches: list[tuple[object, np.ndarray, list]] = []

        def shifted(feats_, templates, seeds, *args, **kwargs):
            found = search(feats_, templates, seeds, *args, **kwargs)
            # The photo's views all under the bar; the outline's moved by
            # outline_shift.
            shift = (bar - 1.0 - max(c.log_likelihood_ratio for c in found) if feats_ is feats
                     else outline_shift) if found else 0.0
            found = [replace(c, log_likelihood_ratio=c.log_likelihood_ratio + shift)
                     for c in found]
            searches.append((feats_, np.array(seeds), found))
            return found

        with monkeypatch.context() as patch:
            patch.setattr(localize_module, "search_views", shifted)
            out = localize_module._colour_locations(
                orange_model, colour, feats, view_templates(orange_model),
                chance_rates(feats), AlignConfig(), [])
        return out, searches

    kept, searches = located(1e4)
    near = [loc for loc in kept
            if np.hypot(*(loc.candidates[0].sim[:2] - [200.0, 150.0])) < 40]
    assert near
    photo = [seeds for f, seeds, _ in searches if f is feats]
    on_outline = {id(found[0]): seeds for f, seeds, found in searches
                  if f is not feats and found}
    for loc in kept:
        # The outline's own views, found from the seeds of a photo search,
        # with nothing left to rival them.
        assert id(loc.candidates[0]) in on_outline
        assert any(np.array_equal(on_outline[id(loc.candidates[0])], s) for s in photo)
        assert loc.colour_rivals == () and loc.outline_only
        assert loc.evidence > bar
    nothing, _ = located(-1e4)
    assert nothing == []


def test_a_colour_location_gets_the_views_of_its_colours_outline(orange_model, monkeypatch):
    """Each colour location is also searched on the outline of the part's
    colour (:meth:`_ColourScene.outline_features`, made once per image),
    from the seeds of its photo search; the views found there that the
    photo's search did not find are the location's colour rivals."""
    import viewloc_core.localize as localize_module
    from viewloc_core.align import AlignConfig
    from viewloc_core.edge_evidence import chance_rates
    from viewloc_core.features import extract_features
    from viewloc_core.view_search import view_templates

    # The clutter gives the photo's edges what the colour's outline has not.
    image = _orange_disc_in_grey_clutter()
    colour = localize_module._ColourScene.of(orange_model, image, 1.0)
    assert colour is not None
    feats = extract_features(image)
    outlines: list[object] = []
    outline_features = localize_module._ColourScene.outline_features
    searches: list[tuple[object, np.ndarray, list]] = []
    search = localize_module.search_views

    def spied_outline(self):
        outlines.append(outline_features(self))
        return outlines[-1]

    def spied_search(feats_, templates, seeds, *args, **kwargs):
        found = search(feats_, templates, seeds, *args, **kwargs)
        if feats_ is feats:  # a disc is no bracket: kept whatever its evidence
            found = [replace(c, log_likelihood_ratio=c.log_likelihood_ratio + 1e4)
                     for c in found]
        searches.append((feats_, np.array(seeds), found))
        return found

    monkeypatch.setattr(localize_module._ColourScene, "outline_features", spied_outline)
    monkeypatch.setattr(localize_module, "search_views", spied_search)
    located = localize_module._colour_locations(
        orange_model, colour, feats, view_templates(orange_model), chance_rates(feats),
        AlignConfig(), [])
    assert located and len(outlines) == 1
    # The photo's searches and the outline's, one of each per location kept,
    # the outline's from the same seeds as the photo's before it.
    photo = [(seeds, found) for f, seeds, found in searches if f is feats]
    on_outline = [(seeds, found) for f, seeds, found in searches if f is outlines[0][0]]
    assert len(on_outline) == len(located) and len(photo) >= len(located)
    for loc, (seeds, found) in zip(located, on_outline, strict=True):
        (photo_seeds,) = [s for s, f in photo if f and f[0] is loc.candidates[0]]
        assert np.array_equal(seeds, photo_seeds)
        known = {c.view for c in loc.candidates}
        assert list(loc.colour_rivals) == [c for c in found if c.view not in known]
        assert len(found) <= localize_module.COLOUR_OUTLINE_CANDIDATES
    assert any(loc.colour_rivals for loc in located)
    assert not any(loc.outline_only for loc in located)


def test_every_fit_in_a_colour_scene_meets_the_parts_colour_boundary(
        orange_model, renderer, monkeypatch):
    """With the part's colours known, every refinement of a colour scene runs
    on the edges with the colour boundary added
    (:func:`viewloc_core.colour_edges.with_colour_boundary`, once per image,
    on the posterior of the full-resolution image); the same scene in grey has no colour cue
    and its fits run on the image's own edges."""
    import viewloc_core.localize as localize_module

    camera = _CAMERA
    pose = Pose(trimesh.transformations.euler_matrix(0.5, -0.4, 0.9)[:3, :3],
                np.array([30.0, -20.0, 520.0]))
    image = _on_grey_table(renderer, [(coloured_bracket(ORANGE), pose)])
    merged: list[object] = []
    fitted_on: list[object] = []
    add_boundary = localize_module.with_colour_boundary
    refine = localize_module.refine_pose

    def recorded_boundary(edges, posterior, *args, **kwargs):
        # The part's colour is read at the image's own resolution.
        assert posterior.shape == image.shape[:2]
        merged.append(add_boundary(edges, posterior, *args, **kwargs))
        return merged[-1]

    def recorded_refine(edges, *args, **kwargs):
        fitted_on.append(edges)
        return refine(edges, *args, **kwargs)

    monkeypatch.setattr(localize_module, "with_colour_boundary", recorded_boundary)
    monkeypatch.setattr(localize_module, "refine_pose", recorded_refine)
    dets = localize(orange_model, image, camera).detections
    assert dets and np.linalg.norm(dets[0].pose.t_m2c - pose.t_m2c) < 10.0
    assert len(merged) == 1 and fitted_on and all(e is merged[0] for e in fitted_on)
    merged.clear()
    fitted_on.clear()
    grey = np.repeat(image.mean(axis=2, keepdims=True), 3, axis=2).astype(np.uint8)
    localize(orange_model, grey, camera, LocalizeOptions(min_score=0.0))
    assert not merged and fitted_on
