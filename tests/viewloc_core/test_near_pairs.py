"""Pairs within a reach of their own: against every pair, and in the grouping."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from viewloc_core import features
from viewloc_core.features import FeatureConfig, _junctions, _parallel_pairs
from viewloc_core.near_pairs import pairs_within


def _every_pair(xy: np.ndarray, reach: np.ndarray, within_both: bool) -> list[tuple[int, int]]:
    """The pairs by testing each one (the reach slack aside)."""
    found = []
    for i in range(len(xy)):
        for j in range(i + 1, len(xy)):
            limit = min(reach[i], reach[j]) if within_both else max(reach[i], reach[j])
            if np.hypot(*(xy[i] - xy[j])) <= limit:
                found.append((i, j))
    return found


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(0, 50), within_both=st.booleans(),
       shared_reach=st.booleans(), on_a_grid=st.booleans())
def test_finds_every_pair_once(seed: int, n: int, within_both: bool, shared_reach: bool,
                               on_a_grid: bool) -> None:
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, 60.0, (n, 2))
    if on_a_grid:
        # Ties in x (the search's sort key) and in distance.
        xy = np.round(xy / 5.0) * 5.0
    reach = np.full(n, rng.uniform(0.0, 20.0)) if shared_reach else rng.uniform(0.0, 20.0, n)
    first, second = pairs_within(xy, reach, within_both)
    assert np.all(first < second)
    found = sorted(zip(first.tolist(), second.tolist(), strict=True))
    assert found == _every_pair(xy, reach, within_both)


def test_more_pairs_than_its_first_room() -> None:
    # Every pair of 200 points: the output grows past its 4 n first room.
    xy = np.random.default_rng(0).uniform(0.0, 5.0, (200, 2))
    first, second = pairs_within(xy, np.full(200, 10.0), within_both=True)
    assert len(first) == 200 * 199 // 2
    assert len(set(zip(first.tolist(), second.tolist(), strict=True))) == len(first)


def test_order_is_fixed_by_the_points() -> None:
    xy = np.random.default_rng(1).uniform(0.0, 40.0, (80, 2))
    reach = np.random.default_rng(2).uniform(0.0, 15.0, 80)
    a = pairs_within(xy, reach, within_both=False)
    b = pairs_within(xy.copy(), reach.copy(), within_both=False)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])


def test_rejects_a_reach_per_point_missing() -> None:
    with pytest.raises(ValueError, match="3 points but 2 reaches"):
        pairs_within(np.zeros((3, 2)), np.ones(2), within_both=True)


def _all_pairs(xy: np.ndarray, reach: np.ndarray,
               within_both: bool) -> tuple[np.ndarray, np.ndarray]:
    """Every pair of rows, as the grouping's candidates (in place of
    :func:`pairs_within`, whose signature it takes)."""
    i, j = np.triu_indices(len(xy), k=1)
    return i.astype(np.int64), j.astype(np.int64)


def _sorted_rows(parts: tuple[np.ndarray, ...]) -> np.ndarray:
    rows = np.column_stack([np.asarray(x, np.float64).reshape(len(parts[0]), -1)
                            for x in parts])
    return rows[np.lexsort(rows.T[::-1])]


@pytest.mark.parametrize("seed", range(3))
def test_grouping_keeps_what_every_pair_would_give(seed: int,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    # Segments of very different lengths (a few long ones among many short
    # ones, as in clutter): the per-segment reach must lose no junction or
    # parallel pair that testing every pair of segments finds.
    rng = np.random.default_rng(seed)
    n = 120
    start = rng.uniform(0.0, 300.0, (n, 2))
    length = np.where(rng.random(n) < 0.1, rng.uniform(80.0, 200.0, n), rng.uniform(4.0, 20.0, n))
    angle = rng.choice([0.0, 0.5 * np.pi, 0.25 * np.pi], n) + rng.normal(0.0, 0.05, n)
    end = start + length[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])
    seg = np.column_stack([start, end]).astype(np.float32)
    config = FeatureConfig()
    junctions = _junctions(seg, config)[0]
    parallel = _parallel_pairs(seg, config)
    monkeypatch.setattr(features, "pairs_within", _all_pairs)
    assert len(parallel[0]) > 0 and len(junctions[0]) > 0
    np.testing.assert_array_equal(_sorted_rows(_parallel_pairs(seg, config)),
                                  _sorted_rows(parallel))
    np.testing.assert_array_equal(_sorted_rows(_junctions(seg, config)[0]),
                                  _sorted_rows(junctions))
