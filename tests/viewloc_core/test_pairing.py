"""The strongest attribute pairings: the compiled passes against brute force."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from viewloc_core import pairing
from viewloc_core.pairing import (
    SAMPLE_STRIDE,
    PairingSet,
    _halves,
    _sorted,
    _visits,
    strongest_pairings,
)


def _brute_force(sets: list[PairingSet], gate: float, max_pairings: int) -> set[tuple[int, int]]:
    """Every pair within the gate, the strongest ``max_pairings`` of them."""
    rows, strength = [], []
    for s in sets:
        d2 = ((s.image_z[:, None, :] - s.model_z[None, :, :]) ** 2).sum(axis=2)
        i, j = np.nonzero(d2 <= gate**2)
        rows += list(zip(s.image_rows[i].tolist(), s.model_rows[j].tolist(), strict=True))
        strength += list(s.image_term[i] + s.model_term[j] - 0.5 * d2[i, j])
    keep = np.argsort(-np.asarray(strength))[:max_pairings]
    return {rows[n] for n in keep}


def _random_set(rng: np.random.Generator, n_image: int, n_model: int, offset: int
                ) -> PairingSet:
    """Features of one kind: two attributes over a few gate widths, terms
    that vary much (image) and little (model), as the alignment's do."""
    return PairingSet(
        image_rows=offset + np.arange(n_image, dtype=np.int64),
        model_rows=offset + 1000 + rng.permutation(n_model).astype(np.int64),
        image_z=rng.uniform(0.0, 12.0, (n_image, 2)),
        model_z=rng.uniform(0.0, 12.0, (n_model, 2)),
        image_term=rng.normal(0.0, 1.5, n_image),
        model_term=rng.normal(-0.3, 0.1, n_model),
    )


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(0, 3000), st.integers(1, 3))
def test_the_strongest_pairings_are_those_of_brute_force(seed, max_pairings, n_kinds):
    rng = np.random.default_rng(seed)
    sets = [_random_set(rng, int(rng.integers(0, 120)), int(rng.integers(0, 150)), 10000 * k)
            for k in range(n_kinds)]
    image_rows, model_rows = strongest_pairings(sets, 2.5, max_pairings)
    got = list(zip(image_rows.tolist(), model_rows.tolist(), strict=True))
    assert len(got) == len(set(got))  # no pairing twice
    assert set(got) == _brute_force(sets, 2.5, max_pairings)


def test_all_pairings_when_there_are_fewer_than_wanted():
    rng = np.random.default_rng(3)
    sets = [_random_set(rng, 40, 60, 0)]
    image_rows, _ = strongest_pairings(sets, 2.5, 10**6)
    assert len(image_rows) == len(_brute_force(sets, 2.5, 10**6)) > 0


def test_a_misleading_sample_still_gives_the_strongest():
    """The sampled image features (every SAMPLE_STRIDE-th) pair strongly and
    the others weakly: the cut the sample suggests keeps too few pairings,
    and the passes reach further until they are enough."""
    rng = np.random.default_rng(5)
    s = _random_set(rng, 400, 300, 0)
    term = np.full(400, -4.0)
    term[::SAMPLE_STRIDE] = 4.0
    s = PairingSet(s.image_rows, s.model_rows, s.image_z, s.model_z, term, s.model_term)
    want = _brute_force([s], 2.5, 5000)
    image_rows, model_rows = strongest_pairings([s], 2.5, 5000)
    assert set(zip(image_rows.tolist(), model_rows.tolist(), strict=True)) == want
    # The cut lies among the weak image features' pairings.
    assert len(want) == 5000 and np.any(term[np.array([i for i, _ in want])] < 0)


def test_undefined_kinds_and_empty_sides_pair_with_nothing():
    rng = np.random.default_rng(7)
    full = _random_set(rng, 30, 30, 0)
    empty = _random_set(rng, 0, 30, 5000)
    image_rows, model_rows = strongest_pairings([empty], 2.5, 100)
    assert len(image_rows) == len(model_rows) == 0
    image_rows, _ = strongest_pairings([empty, full], 2.5, 100)
    assert set(image_rows.tolist()) <= set(full.image_rows.tolist())


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 3000), st.integers(1, 3))
def test_two_runs_give_the_pairings_of_one_in_the_same_order(seed, max_pairings, n_kinds):
    """Shared by the two cores, the passes give exactly what one pass over
    all features gives, pairing for pairing and in the same order (the
    alignment's later sorts break ties by it)."""
    rng = np.random.default_rng(seed)
    sets = [_random_set(rng, int(rng.integers(0, 120)), int(rng.integers(0, 150)), 10000 * k)
            for k in range(n_kinds)]
    with _split_above(10**12):
        one = strongest_pairings(sets, 2.5, max_pairings)
    with _split_above(0):
        two = strongest_pairings(sets, 2.5, max_pairings)
    assert np.array_equal(one[0], two[0]) and np.array_equal(one[1], two[1])


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 4))
def test_the_two_runs_cover_every_feature_once_in_order(seed, n_kinds):
    rng = np.random.default_rng(seed)
    sets = [_sorted(_random_set(rng, int(rng.integers(1, 80)), int(rng.integers(1, 90)),
                                10000 * k)) for k in range(n_kinds)]
    with _split_above(0):
        runs = _halves(sets, _visits(sets, 2.5))
    laid_end_to_end = [(k, i) for run in runs for k, start, stop in run
                       for i in range(start, stop)]
    assert laid_end_to_end == [(k, i) for k, s in enumerate(sets)
                               for i in range(len(s.image_rows))]
    with _split_above(10**12):
        assert len(_halves(sets, _visits(sets, 2.5))) == 1


@contextmanager
def _split_above(visits: int) -> Iterator[None]:
    """:data:`MIN_SPLIT_VISITS` set to ``visits`` for a while."""
    kept = pairing.MIN_SPLIT_VISITS
    pairing.MIN_SPLIT_VISITS = visits
    try:
        yield
    finally:
        pairing.MIN_SPLIT_VISITS = kept
