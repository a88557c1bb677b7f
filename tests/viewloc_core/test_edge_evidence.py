"""Edge evidence of templates: the clutter model and the split of hits by contrast."""

from dataclasses import replace

import cv2
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.viewloc_core.conftest import faint_noise
from viewloc_core.edge_evidence import (
    SAMPLE_ANY,
    SAMPLE_CREASE,
    SAMPLE_HIT_RATES,
    SAMPLE_INTERIOR,
    SAMPLE_OUTLINE,
    TRUE_HIT_RATE,
    ChanceRates,
    _log_ratios,
    chance_rates,
    lay_over_templates,
)
from viewloc_core.features import ORIENTATION_BINS, extract_features, orientation_bin
from viewloc_core.sample_evidence import MISS, STRONG_HIT, WEAK_HIT

rates = st.floats(0.005, 0.95)
shares = st.floats(0.01, 0.99)


@settings(max_examples=200, deadline=None)
@given(rates, shares, st.sampled_from(range(len(SAMPLE_HIT_RATES))))
def test_the_ratios_are_of_two_proper_distributions(edge, share, sample_class):
    """Weighted by the clutter's own probabilities, the ratios of each
    sample class give the object's, which sum to one; both models' shares
    are in (0, 1)."""
    chance = ChanceRates(np.full(ORIENTATION_BINS, edge), np.full(ORIENTATION_BINS, edge * share))
    table = _log_ratios(chance)
    assert table.shape == (len(SAMPLE_HIT_RATES) * ORIENTATION_BINS, 3)
    miss, weak, strong = table[sample_class * ORIENTATION_BINS].T
    rate = SAMPLE_HIT_RATES[sample_class]
    clutter = np.array([edge * (1 - share), edge * share, 1 - edge])
    object_probability = clutter * np.exp(np.array([weak, strong, miss]))
    assert np.all((object_probability > 0) & (object_probability < 1))
    assert abs(object_probability.sum() - 1.0) < 1e-9
    # A strong hit is worth more than a hit not told apart, a weak one less;
    # the object's hits are as often hits as before the split.
    plain = np.log(rate / edge)
    assert strong > plain > weak
    assert abs(object_probability[:2].sum() - rate) < 1e-9


def test_a_missing_outline_costs_more_than_a_missing_edge_inside():
    """The outline is found at the true pose more often than anything else:
    its miss is the strongest evidence against a hypothesis, its hit the
    strongest for it; unclassified samples keep the one rate of before."""
    chance = ChanceRates(np.full(ORIENTATION_BINS, 0.2), np.full(ORIENTATION_BINS, 0.05))
    rows = _log_ratios(chance)[::ORIENTATION_BINS]
    assert SAMPLE_HIT_RATES[SAMPLE_ANY] == TRUE_HIT_RATE
    for other in (SAMPLE_INTERIOR, SAMPLE_CREASE, SAMPLE_ANY):
        assert rows[SAMPLE_OUTLINE, MISS] < rows[other, MISS]
        assert rows[SAMPLE_OUTLINE, WEAK_HIT] > rows[other, WEAK_HIT]


@settings(max_examples=50, deadline=None)
@given(rates)
def test_the_split_vanishes_where_all_edges_are_strong_or_none(edge):
    # Two bins per class here: each class's rows at its own rate.
    plain = np.repeat(np.log(np.array(SAMPLE_HIT_RATES) / edge), 2)
    all_strong = _log_ratios(ChanceRates(np.full(2, edge), np.full(2, edge)))
    none_strong = _log_ratios(ChanceRates(np.full(2, edge), np.zeros(2)))
    np.testing.assert_allclose(all_strong[:, STRONG_HIT], plain, atol=1e-5)
    np.testing.assert_allclose(none_strong[:, WEAK_HIT], plain, atol=1e-5)
    np.testing.assert_allclose(all_strong[:, MISS], none_strong[:, MISS])


def _square_template(x0, y0, x1, y1, step=4.0):
    """Edge samples (1, P) along a rectangle's sides, image pixels at the identity."""
    top = np.arange(x0, x1, step)
    side = np.arange(y0, y1, step)
    px = np.concatenate([top, top, np.full_like(side, x0), np.full_like(side, x1)])
    py = np.concatenate([np.full_like(top, y0), np.full_like(top, y1), side, side])
    theta = np.concatenate([np.zeros(2 * len(top)), np.full(2 * len(side), np.pi / 2)])
    bins = orientation_bin(theta).astype(np.uint8)
    return (px[None].astype(np.float32), py[None].astype(np.float32), bins[None],
            np.ones((1, len(px)), bool))


def test_a_contrasted_part_gains_on_faint_texture():
    """A bright square on faint noise: laid over the square, the template's
    evidence rises with the split, and its lead over the same template laid
    over the noise alone grows."""
    img = faint_noise((300, 400), 5, 1.5, 120, 6)
    cv2.rectangle(img, (60, 50), (170, 140), 200, thickness=-1)
    feats = extract_features(img)
    template = _square_template(60, 50, 170, 140)
    sims = np.array([[0.0, 0.0, 0.0, 1.0], [200.0, 120.0, 0.0, 1.0]])
    rows = np.zeros(2, np.int64)
    chance = chance_rates(feats)
    split = lay_over_templates(feats, *template, rows, sims, chance)[0]
    # Every edge taken as strong: the evidence before the split.
    alike = replace(feats, strong_bits=feats.orientation_bits)
    unsplit = lay_over_templates(alike, *template, rows, sims, chance_rates(alike))[0]
    assert split[0] > 1.1 * unsplit[0] > 0
    assert unsplit[1] < 0
    # The square's lead over the texture grows by a tenth or more.
    assert split[0] - split[1] > 1.1 * (unsplit[0] - unsplit[1])


def test_an_images_table_is_built_once_and_is_the_table_of_its_rates():
    chance = ChanceRates(np.full(ORIENTATION_BINS, 0.2), np.full(ORIENTATION_BINS, 0.05))
    table = chance.log_ratio
    assert chance.log_ratio is table  # every kernel call of the image reads this one
    np.testing.assert_array_equal(table, _log_ratios(chance))
