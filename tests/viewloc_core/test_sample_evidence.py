"""Template samples laid over an orientation map: hits, misses, outside, padding."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from viewloc_core.features import ORIENTATION_BINS, orientation_turn, wanted_bits
from viewloc_core.sample_evidence import lay_over, lay_over_grid, similarity_terms


def test_hits_misses_outside_and_padding_each_count_as_they_should():
    bits = np.zeros((20, 30), np.uint16)
    bits[5, 10] = 1 << 3  # an edge of bin 3 at (10, 5)
    wanted = wanted_bits(np.arange(ORIENTATION_BINS)).astype(np.uint16)
    # One template: a sample on the edge, one on empty image, one outside,
    # one padding. Scale 2, no turn, shifted by (4, 1).
    px = np.array([[3.0, 5.0, 40.0, 3.0]], np.float32)
    py = np.array([[2.0, 2.0, 2.0, 2.0]], np.float32)
    bins = np.array([[3, 3, 3, 3]], np.uint8)
    valid = np.array([[True, True, True, False]])
    log_hit = np.arange(ORIENTATION_BINS) + 1.0
    log_strong_hit = log_hit + 0.25
    log_miss = -np.arange(ORIENTATION_BINS) - 0.5
    log_ratio = np.stack([log_miss, log_hit, log_strong_hit], axis=1)
    one = np.ones(1, np.float32)
    weak = np.zeros_like(bits)

    def laid(strong_bits, turn):
        return lay_over(bits, strong_bits, wanted, px, py, bins, valid, np.zeros(1, np.int64),
                        2 * one, 0 * one, 4 * one, one, np.full(1, turn, np.uint8), log_ratio)

    llr, hits, n_valid, best = laid(weak, 0)
    assert list(hits) == [1] and list(n_valid) == [3]
    assert llr[0] == log_hit[3] + log_miss[3]
    # Had every sample found its edge, of the better kind (here the strong).
    assert best[0] == 2 * log_strong_hit[3]
    # The same edge, strong: the hit counts at the strong odds.
    llr_s, hits_s, _, _ = laid(bits, 0)
    assert list(hits_s) == [1]
    assert llr_s[0] == log_strong_hit[3] + log_miss[3]
    # Turned by one bin, the sample's bin 4 is still confirmed by a bin-3
    # edge (the spread map's tolerance), at bin 4's odds.
    llr_t, hits_t, _, _ = laid(weak, 1)
    assert list(hits_t) == [int(wanted[4] & bits[5, 10] != 0)]
    assert llr_t[0] == (log_hit[4] if hits_t[0] else log_miss[4]) + log_miss[4]


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_the_grid_gives_each_pair_what_lay_over_gives_it(seed):
    rng = np.random.default_rng(seed)
    bits = rng.integers(0, 2**16, (40, 50)).astype(np.uint16)
    bits[rng.random(bits.shape) < 0.6] = 0
    strong_bits = bits & rng.integers(0, 2**16, bits.shape).astype(np.uint16)
    wanted = wanted_bits(np.arange(ORIENTATION_BINS)).astype(np.uint16)
    n_templates, n_points, n_sims = 7, 12, 5
    px = rng.uniform(-15, 15, (n_templates, n_points)).astype(np.float32)
    py = rng.uniform(-15, 15, (n_templates, n_points)).astype(np.float32)
    bins = rng.integers(0, ORIENTATION_BINS, (n_templates, n_points)).astype(np.uint8)
    valid = rng.random((n_templates, n_points)) < 0.8
    views = rng.choice(n_templates, 4, replace=False).astype(np.int64)
    angle = rng.uniform(-np.pi, np.pi, n_sims)
    scale = rng.uniform(0.5, 2.0, n_sims)
    c = (scale * np.cos(angle)).astype(np.float32)
    s = (scale * np.sin(angle)).astype(np.float32)
    x = rng.uniform(-5, 55, n_sims).astype(np.float32)
    y = rng.uniform(-5, 45, n_sims).astype(np.float32)
    turn = rng.integers(0, ORIENTATION_BINS + 1, n_sims).astype(np.uint8)
    log_ratio = np.stack([-rng.uniform(0, 3, ORIENTATION_BINS),
                          rng.uniform(0, 3, ORIENTATION_BINS),
                          rng.uniform(0, 3, ORIENTATION_BINS)], axis=1)
    grid = lay_over_grid(bits, strong_bits, wanted, px, py, bins, valid, views, c, s, x, y, turn,
                         log_ratio)
    # The same pairs built one by one, similarity-major.
    k = np.repeat(np.arange(n_sims), len(views))
    pairs, _, _, _ = lay_over(bits, strong_bits, wanted, px, py, bins, valid,
                              np.tile(views, n_sims), c[k], s[k], x[k], y[k], turn[k],
                              log_ratio)
    np.testing.assert_array_equal(grid, pairs)


def test_a_samples_class_picks_its_rows_of_the_table():
    """Codes ``class * B + bin``: two samples of bin 3 on one edge, of
    classes 0 and 1, read rows 3 and B + 3; turned, each keeps its class."""
    bits = np.zeros((20, 30), np.uint16)
    bits[5, 10] = 1 << 3
    wanted = wanted_bits(np.arange(ORIENTATION_BINS)).astype(np.uint16)
    px = np.array([[3.0, 3.0, 5.0]], np.float32)
    py = np.array([[2.0, 2.0, 2.0]], np.float32)
    codes = np.array([[3, ORIENTATION_BINS + 3, ORIENTATION_BINS + 3]], np.uint8)
    valid = np.ones((1, 3), bool)
    rows = np.arange(2 * ORIENTATION_BINS, dtype=np.float64)
    log_ratio = np.stack([-rows - 0.5, rows + 1.0, rows + 1.25], axis=1)
    one = np.ones(1, np.float32)
    llr, hits, _, best = lay_over(bits, np.zeros_like(bits), wanted, px, py, codes, valid,
                                  np.zeros(1, np.int64), 2 * one, 0 * one, 4 * one, one,
                                  np.zeros(1, np.uint8), log_ratio)
    b = ORIENTATION_BINS
    assert list(hits) == [2]
    assert llr[0] == log_ratio[3, 1] + log_ratio[b + 3, 1] + log_ratio[b + 3, 0]
    assert best[0] == log_ratio[3, 2] + 2 * log_ratio[b + 3, 2]
    # A turn of 15 bins (bin 3 -> 2) stays in each sample's own rows.
    turned, _, _, _ = lay_over(bits, np.zeros_like(bits), wanted, px, py, codes, valid,
                               np.zeros(1, np.int64), 2 * one, 0 * one, 4 * one, one,
                               np.full(1, b - 1, np.uint8), log_ratio)
    hit = bool(wanted[2] & bits[5, 10])
    assert turned[0] == (log_ratio[2, int(hit)] + log_ratio[b + 2, int(hit)]
                         + log_ratio[b + 2, 0])


angles = st.one_of(
    st.floats(-20.0, 20.0, allow_nan=False),
    # Exactly on the boundaries between turns, where rounding decides.
    st.builds(lambda k: (k + 0.5) * np.pi / ORIENTATION_BINS, st.integers(-64, 64)),
)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.floats(-1e4, 1e4), st.floats(-1e4, 1e4), angles,
                          st.floats(1e-3, 50.0)), min_size=0, max_size=30))
def test_the_similarity_terms_are_numpys_to_the_bit(rows):
    """The compiled pass gives the kernels exactly what the array
    expressions gave (positions round to pixels on these values)."""
    sims = np.array(rows, np.float64).reshape(-1, 4)
    cos_scale, sin_scale, x, y, turn = similarity_terms(sims, ORIENTATION_BINS)
    assert np.array_equal(cos_scale, (sims[:, 3] * np.cos(sims[:, 2])).astype(np.float32))
    assert np.array_equal(sin_scale, (sims[:, 3] * np.sin(sims[:, 2])).astype(np.float32))
    assert np.array_equal(x, sims[:, 0].astype(np.float32))
    assert np.array_equal(y, sims[:, 1].astype(np.float32))
    assert np.array_equal(turn, orientation_turn(sims[:, 2]).astype(np.uint8))
    assert turn.dtype == np.uint8 and np.all(turn <= ORIENTATION_BINS)
