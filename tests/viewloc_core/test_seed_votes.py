"""Vote bins of seeds: supports and strongest seeds against plain counting."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from viewloc_core.seed_votes import bin_supports, peak_bins


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(0, 300))
def test_bin_supports_equal_a_plain_count(seed, n):
    rng = np.random.default_rng(seed)
    keys = rng.integers(0, 25, n) * 7919
    vote = rng.integers(1, 4, n) * 0.5  # few levels: ties within bins
    members = np.flatnonzero(rng.random(n) < 0.7)
    support, strongest = bin_supports(keys, vote, members)
    bins = sorted(set(keys[members].tolist()))
    assert len(support) == len(bins)
    for b, key in enumerate(bins):
        in_bin = members[keys[members] == key]
        assert support[b] == vote[in_bin].sum()
        assert strongest[b] == in_bin[np.argmax(vote[in_bin])]  # first of equals


def test_peak_bins_take_exactly_the_seeds_within_reach_of_each_peak():
    rng = np.random.default_rng(2)
    x, y = rng.uniform(0, 200, 400), rng.uniform(0, 150, 400)
    cell = 6.0
    column = np.floor(x / cell).astype(np.int64) + 2
    keys = np.arange(400, dtype=np.int64)  # every seed its own bin
    vote = rng.uniform(0.5, 3.0, 400)
    peak_columns = np.array([10, 25], np.int64)
    centres = np.array([[(10 - 2 + 0.5) * cell, 40.0], [(25 - 2 + 0.5) * cell, 100.0]])
    support, strongest, counts = peak_bins(x, y, column, keys, vote, centres, peak_columns,
                                           2 * cell)
    start = 0
    for centre, count in zip(centres, counts, strict=True):
        want = np.flatnonzero(np.hypot(x - centre[0], y - centre[1]) < 2 * cell)
        assert sorted(strongest[start:start + count].tolist()) == want.tolist()
        np.testing.assert_array_equal(support[start:start + count], vote[want])
        start += count
    assert start == len(support)
