"""View search: which training view explains an image location, and its evidence."""

import cv2
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from tests.viewloc_core.conftest import render_scene
from viewloc_core import view_search
from viewloc_core.camera import Camera
from viewloc_core.edge_evidence import chance_rates
from viewloc_core.features import ORIENTATION_BINS, extract_features
from viewloc_core.pose import Pose, rotation_angle_deg
from viewloc_core.view_search import (
    score_views,
    search_views,
    view_templates,
)

CAM = Camera(520.0, 520.0, 199.5, 149.5, 400, 300)


def _scene(renderer, mesh, model, t_view, angle_deg, clutter):
    """Render training view ``t_view`` turned in-plane by ``angle_deg``; the
    similarity training frame -> image it should be found at."""
    a = np.radians(angle_deg)
    turn = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    z = 650.0
    R = turn @ model.training.R_m2c[t_view]
    t = np.array([30.0, -20.0, z]) - R @ model.origin_offset_mm
    image = render_scene(renderer, mesh, CAM, Pose(R, t), clutter=clutter, rng=3)
    centre = CAM.project(np.array([[30.0, -20.0, z]]))[0]
    sim = np.array([centre[0], centre[1], a, model.d0_mm / z * CAM.fx / model.f_train_px])
    return image, sim, R


def test_the_rendered_view_wins_from_a_perturbed_start(renderer, bracket_mesh, bracket_model):
    model = bracket_model
    templates = view_templates(model)
    for t_view, angle in ((3, 30.0), (17, -100.0)):
        image, sim_true, R_true = _scene(renderer, bracket_mesh, model, t_view, angle, clutter=3)
        feats = extract_features(image)
        start = sim_true + np.array([2.0, -2.0, np.radians(6.0), 0.0])
        start[3] *= 1.05
        found = search_views(feats, templates, start[None], chance_rates(feats))
        assert found
        best = found[0]
        assert np.hypot(*(best.sim[:2] - sim_true[:2])) < 2.0
        assert abs(np.degrees(np.angle(np.exp(1j * (best.sim[2] - sim_true[2]))))) < 3.0
        assert abs(best.sim[3] / sim_true[3] - 1.0) < 0.03
        # The winner is the rendered view or one that looks the same from
        # nearby (the 6D orientation it implies is close to the truth).
        a = best.sim[2]
        turn = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        assert rotation_angle_deg(turn @ model.training.R_m2c[best.view], R_true) < 25.0
        assert best.hit_fraction > 0.7


def test_evidence_is_higher_on_the_object_than_on_clutter(renderer, bracket_mesh, bracket_model):
    model = bracket_model
    templates = view_templates(model)
    image, sim_true, _ = _scene(renderer, bracket_mesh, model, 5, 0.0, clutter=6)
    feats = extract_features(image)
    chance = chance_rates(feats)
    views = np.array([5])
    on, frac_on, evid_on = score_views(feats, templates, views, sim_true[None], chance)
    rng = np.random.default_rng(0)
    elsewhere = np.tile(sim_true, (40, 1))
    elsewhere[:, 0] = rng.uniform(0, CAM.width, 40)
    elsewhere[:, 1] = rng.uniform(0, CAM.height, 40)
    far = np.hypot(elsewhere[:, 0] - sim_true[0], elsewhere[:, 1] - sim_true[1]) > 80
    off, frac_off, evid_off = score_views(feats, templates, np.full(int(far.sum()), 5),
                                          elsewhere[far],
                                          chance)
    assert on[0] > 0 > np.median(off)
    assert on[0] > off.max()
    assert frac_on[0] > np.percentile(frac_off, 90)
    assert evid_on[0] > 0.5 > evid_off.max()


def test_each_templates_direction_is_where_its_camera_looks_from(bracket_model):
    templates = view_templates(bracket_model)
    # The camera looks along its +z: from the part, it lies along -z.
    towards_camera = np.einsum("tji,j->ti", bracket_model.training.R_m2c, [0.0, 0.0, -1.0])
    np.testing.assert_allclose(templates.directions, towards_camera, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(templates.directions, axis=1), 1.0, atol=1e-12)


def test_the_other_sides_candidates_come_after_the_best_and_leave_them_unchanged(
        renderer, bracket_mesh, bracket_model):
    model = bracket_model
    templates = view_templates(model)
    image, sim_true, _ = _scene(renderer, bracket_mesh, model, 17, -100.0, clutter=3)
    feats = extract_features(image)
    chance = chance_rates(feats)
    start = sim_true + np.array([2.0, -2.0, np.radians(6.0), 0.0])
    plain = search_views(feats, templates, start[None], chance, 4)
    both = search_views(feats, templates, start[None], chance, 4, other_side=1)
    assert len(plain) == 4 and len(both) == 5
    for a, b in zip(plain, both[:4], strict=True):
        assert (a.view, a.log_likelihood_ratio) == (b.view, b.log_likelihood_ratio)
        np.testing.assert_array_equal(a.sim, b.sim)
    other = both[4]
    assert other.view not in [c.view for c in plain]
    cos = float(templates.directions[other.view] @ templates.directions[both[0].view])
    assert np.degrees(np.arccos(cos)) >= view_search.OTHER_SIDE_MIN_DEG
    # Seen from the other side, the outline is the first's mirror image: the
    # search fits it to the image's outline as it can, well below the first.
    assert other.log_likelihood_ratio < both[0].log_likelihood_ratio


def test_chance_rates_follow_the_image_clutter():
    rng = np.random.default_rng(1)
    blank = np.full((200, 300, 3), 100, np.uint8)
    busy = blank.copy()
    for _ in range(80):
        p, q = rng.integers(0, 300, 2), rng.integers(0, 200, 2)
        cv2.line(busy, (int(p[0]), int(q[0])), (int(p[1]), int(q[1])), (220, 220, 220), 1)
    quiet = chance_rates(extract_features(blank))
    noisy = chance_rates(extract_features(busy))
    assert quiet.edge.shape == noisy.edge.shape == noisy.strong_edge.shape == (ORIENTATION_BINS,)
    assert np.all(quiet.edge <= 0.01)
    assert np.all(noisy.edge > quiet.edge)
    assert np.all((noisy.edge > 0) & (noisy.edge < 1))
    assert np.all((noisy.strong_edge >= 0) & (noisy.strong_edge <= noisy.edge))


def test_scores_match_a_sample_by_sample_count(renderer, bracket_mesh, bracket_model):
    """The vectorised scoring (whole views and coarse subsets) against a
    plain loop over samples: hit where the spread map has the sample's
    turned bin or a neighbour, samples outside the image add nothing."""
    from viewloc_core.edge_evidence import OUTLINE_SCALE_EXPONENT, _log_ratios
    from viewloc_core.features import wanted_bits
    from viewloc_core.view_search import _score_coarse

    model = bracket_model
    templates = view_templates(model)
    image, sim_true, _ = _scene(renderer, bracket_mesh, model, 5, 20.0, clutter=4)
    feats = extract_features(image)
    chance = chance_rates(feats)
    # Rows per sample class (outline, crease, interior) and bin.
    log_miss, log_hit, log_strong_hit = _log_ratios(chance).T
    # The clutter of this scene has strong edges and weak ones, so both
    # kinds of hit are counted below.
    assert 0 < chance.strong_edge.sum() < chance.edge.sum()
    rng = np.random.default_rng(2)
    views = rng.integers(0, len(templates), 12)
    sims = np.tile(sim_true, (12, 1))
    sims[:, :2] += rng.normal(0, 30, (12, 2))
    sims[0, :2] = (5.0, 5.0)  # partly outside the image
    sims[:, 2] += rng.uniform(-np.pi, np.pi, 12)
    views[1], sims[1] = 5, sim_true  # and one that fits
    llr, frac, evid = score_views(feats, templates, views, sims, chance)
    h, w = feats.shape
    for i, (t, s) in enumerate(zip(views, sims, strict=True)):
        pts = templates.pts[t][templates.valid[t]]
        c, sn = s[3] * np.cos(s[2]), s[3] * np.sin(s[2])
        turn = int(np.floor(np.mod(s[2], np.pi) / np.pi * ORIENTATION_BINS + 0.5))
        total = found_all = 0.0
        hits = 0
        classes = templates.bins8[t][templates.valid[t]] // ORIENTATION_BINS
        for p, b0, k in zip(pts, templates.bins[t][templates.valid[t]], classes, strict=True):
            u = int(np.rint(np.float32(c) * np.float32(p[0]) - np.float32(sn) * np.float32(p[1])
                            + np.float32(s[0])))
            v = int(np.rint(np.float32(sn) * np.float32(p[0]) + np.float32(c) * np.float32(p[1])
                            + np.float32(s[1])))
            if not (0 <= u < w and 0 <= v < h):
                continue
            b = (int(b0) + turn) % ORIENTATION_BINS
            wanted = int(wanted_bits(np.array([b]))[0])
            hit = bool(int(feats.orientation_bits[v, u]) & wanted)
            strong = bool(int(feats.strong_bits[v, u]) & wanted)
            hits += hit
            r = int(k) * ORIENTATION_BINS + b
            total += (log_strong_hit[r] if strong else log_hit[r]) if hit else log_miss[r]
            found_all += max(log_hit[r], log_strong_hit[r])
        length = templates.length_px[t] * s[3] ** OUTLINE_SCALE_EXPONENT
        assert llr[i] == pytest.approx(total * length, rel=1e-9, abs=1e-9)
        assert frac[i] == pytest.approx(hits / len(pts))
        assert evid[i] == pytest.approx(total / max(found_all, 1e-9), rel=1e-9, abs=1e-9)
    # The coarse screening scores exactly the coarse subsets.
    coarse = _score_coarse(feats, templates, views, sims, chance)
    subset = score_views(feats, templates, views, sims, chance, templates.coarse[views])
    np.testing.assert_array_equal(coarse, subset[0])
    assert frac[1] > 0.5


def test_best_member_is_the_member_of_highest_coverage(renderer, bracket_mesh, bracket_model):
    """The batched choice equals composing and covering member by member."""
    from viewloc_core import similarity as sim2
    from viewloc_core.align import coverage
    from viewloc_core.features import orientation_bin
    from viewloc_core.view_search import best_member

    model = bracket_model
    tr = model.training
    image, sim_true, _ = _scene(renderer, bracket_mesh, model, 5, 35.0, clutter=2)
    feats = extract_features(image)
    rng = np.random.default_rng(8)
    for model_view in range(len(model.model_views)):
        members = np.flatnonzero(tr.model_view == model_view)
        sim = sim_true + np.array([*rng.normal(0, 3, 2), rng.normal(0, 0.2), 0.0])
        covs = [coverage(feats, sim2.compose(sim, tr.sim_to_model[t]),
                         tr.edge_xy[t].astype(np.float64), orientation_bin(tr.edge_theta[t]))
                for t in members]
        t_best, sim_best = best_member(model, model_view, sim, feats)
        assert t_best == members[int(np.argmax(covs))]
        np.testing.assert_array_equal(sim_best, sim2.compose(sim, tr.sim_to_model[t_best]))


def test_offsets_find_a_view_whose_seed_is_off_by_more_than_the_spread(
        renderer, bracket_mesh, bracket_model):
    """A seed 9 px off (beyond the spread map's 2 px and the fit's reach)
    is found on a grid of screened offsets, and only the best seeds are
    kept for the full grid."""
    model = bracket_model
    templates = view_templates(model)
    errors = {"plain": [], "offsets": []}
    for t_view, angle in ((3, 30.0), (17, -100.0), (40, 60.0)):
        image, sim_true, _ = _scene(renderer, bracket_mesh, model, t_view, angle, clutter=3)
        feats = extract_features(image)
        start = sim_true + np.array([7.0, -6.0, 0.0, 0.0])
        offsets = 7.0 * np.array([(dx, dy) for dy in (-1, 0, 1) for dx in (-1, 0, 1)], float)
        for kind, kwargs in (("plain", {}), ("offsets", {"offsets_px": offsets,
                                                          "kept_seeds": 2,
                                                          "screen_angles_deg": (0.0,)})):
            found = search_views(feats, templates, start[None], chance_rates(feats), **kwargs)
            errors[kind].append(np.hypot(*(found[0].sim[:2] - sim_true[:2])) if found else 1e9)
    assert max(errors["offsets"]) < 2.0
    assert max(errors["plain"]) > 4.0


def test_a_large_screen_is_prescreened_on_fewer_samples(
        renderer, bracket_mesh, bracket_model, monkeypatch):
    """Every angle and scale at 9 offsets around a location (as the colour
    locations search) is over PRESCREEN_MIN_PAIRS pairs: the pairs a screen on
    PRESCREEN_POINTS samples ranks best get the full score, and the search
    ends where the full screen of every pair ends."""
    model = bracket_model
    templates = view_templates(model)
    offsets = 6.0 * np.array([(dx, dy) for dy in (-1, 0, 1) for dx in (-1, 0, 1)], float)
    for t_view, angle in ((3, 30.0), (17, -100.0), (40, 60.0)):
        image, sim_true, _ = _scene(renderer, bracket_mesh, model, t_view, angle, clutter=3)
        feats = extract_features(image)
        chance = chance_rates(feats)
        seeds = np.array([[sim_true[0] + 4.0, sim_true[1] - 3.0, np.radians(a), sim_true[3] * f]
                          for f in (0.9, 1.0, 1.1) for a in range(0, 360, 15)])
        pairs = len(seeds) * len(offsets) * len(templates)
        assert pairs > view_search.PRESCREEN_MIN_PAIRS

        shifted = view_search._shifted(seeds, offsets)
        views = np.tile(np.arange(len(templates)), len(shifted))
        sims = np.repeat(shifted, len(templates), axis=0)
        screened = view_search._screen(feats, templates, shifted, chance)
        full = view_search._score_coarse(feats, templates, views, sims, chance)
        # The grid's scores are those of the pairs built one by one.
        np.testing.assert_array_equal(
            view_search._score_coarse_grid(feats, templates, shifted, chance), full)
        kept = np.isfinite(screened)
        assert kept.sum() == int(view_search.PRESCREEN_KEPT * len(views))
        np.testing.assert_array_equal(screened[kept], full[kept])
        # The best pairs of the full screen are among those kept.
        top = np.argsort(-full)[:20]
        assert kept[top[0]] and kept[top].sum() >= 16

        prescreened = search_views(feats, templates, seeds, chance, 6, offsets, 24, (0.0,))[0]
        with monkeypatch.context() as patch:
            patch.setattr(view_search, "PRESCREEN_MIN_PAIRS", 10**9)
            full_best = search_views(feats, templates, seeds, chance, 6, offsets, 24, (0.0,))[0]
        assert np.hypot(*(prescreened.sim[:2] - sim_true[:2])) < 2.0
        assert prescreened.log_likelihood_ratio >= 0.97 * full_best.log_likelihood_ratio


def test_the_grid_is_seed_major_then_angle_then_scale():
    seeds = np.array([[10.0, 20.0, 0.5, 1.0], [30.0, 40.0, -1.0, 2.0]])
    grid = view_search._grid_sims(seeds, (0.0, 0.25), (0.9, 1.0, 1.1))
    assert grid.shape == (12, 4)
    k = 0
    for seed in seeds:
        for a in (0.0, 0.25):
            for f in (0.9, 1.0, 1.1):
                assert grid[k].tolist() == [seed[0], seed[1], seed[2] + a, seed[3] * f]
                k += 1


def _best_entries_by_scatter(views, llr, count):
    """The per-view choice the searches made before reading columns: a
    scatter-maximum over all (view, similarity) entries, the first entry
    at each view's best, the ``count`` best views' entries best first,
    views of equal score in the order of their ids."""
    best = np.full(int(views.max()) + 1, -np.inf)
    np.maximum.at(best, views, llr)
    at_best = np.flatnonzero(llr == best[views])
    _, first = np.unique(views[at_best], return_index=True)
    entries = at_best[first]
    return entries[np.argsort(-llr[entries], kind="stable")[:count]]


@given(st.data())
def test_a_views_best_is_read_from_its_column_as_a_scatter_maximum_finds_it(data):
    n_views = data.draw(st.integers(1, 12))
    n_sims = data.draw(st.integers(1, 6))
    count = data.draw(st.integers(1, 14))
    view_ids = np.array(data.draw(st.permutations(range(3 * n_views)))[:n_views], np.int64)
    # Few distinct values, -inf among them: ties within and across views.
    llr = np.array(data.draw(st.lists(st.sampled_from([-np.inf, -1.0, 0.0, 0.5, 2.0]),
                                      min_size=n_sims * n_views, max_size=n_sims * n_views)))
    row, view_best = view_search._column_best(llr.reshape(n_sims, n_views))
    columns = view_search._best_columns(view_ids, view_best, count)
    entries = row[columns] * n_views + columns
    expected = _best_entries_by_scatter(np.tile(view_ids, n_sims), llr, count)
    assert entries.tolist() == expected.tolist()


@given(seed=st.integers(0, 2**31 - 1), size=st.integers(2, 3000), share=st.floats(0.0, 1.0),
       levels=st.sampled_from([None, 3, 50]))
def test_largest_are_the_largest(seed: int, size: int, share: float, levels: int | None) -> None:
    # Any values (few distinct ones: ties at the n-th place; -inf among
    # them, as a screen's), any n: the values taken are the n largest.
    rng = np.random.default_rng(seed)
    values = rng.normal(size=size)
    if levels is not None:
        values = np.floor(values * levels / 4.0)
    values[rng.random(size) < 0.2] = -np.inf
    n = min(size - 1, max(1, int(share * size)))
    taken = view_search._largest(values, n)
    assert len(np.unique(taken)) == n
    np.testing.assert_array_equal(np.sort(values[taken]), np.sort(values)[-n:])
