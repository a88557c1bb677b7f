"""Evidence against outlines that the image's lines run across."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from viewloc_core.features import extract_features
from viewloc_core.line_crossing import (
    OBJECT_CROSSED_RATE,
    chance_crossed_rate,
    crossed,
    crossing_evidence,
    crossing_log_ratios,
)

CELL_PX = 20


def _checkerboard(shape=(300, 400)):
    """Dark and light cells of CELL_PX pixels, uint8 grey."""
    rows, cols = np.indices(shape)
    return np.where(((rows // CELL_PX) + (cols // CELL_PX)) % 2 == 0, 70, 180).astype(np.uint8)


def _square_outline(x0, y0, x1, y1, step=3.0):
    """Samples along a square's sides and their tangent angles, (P, 2) and (P,)."""
    top = np.arange(x0 + step, x1 - step, step)
    side = np.arange(y0 + step, y1 - step, step)
    uv = np.concatenate([np.stack([top, np.full_like(top, y0)], 1),
                         np.stack([top, np.full_like(top, y1)], 1),
                         np.stack([np.full_like(side, x0), side], 1),
                         np.stack([np.full_like(side, x1), side], 1)])
    tangent = np.concatenate([np.zeros(2 * len(top)), np.full(2 * len(side), np.pi / 2)])
    return uv, tangent


def _part_on_checkerboard():
    """A plain square part laid over the checkerboard off its grid: the part's
    corners at (107, 87) and (193, 173)."""
    img = _checkerboard()
    img[87:174, 107:194] = 125
    return extract_features(img)


def test_a_phantom_on_the_grid_is_crossed_and_the_part_is_not():
    """Along a square snapped onto the checkerboard's lines, the lines at right
    angles run on across it every cell; along the part's own outline they
    end there (the part hides them)."""
    feats = _part_on_checkerboard()
    part = crossed(feats, *_square_outline(107, 87, 193, 173))
    phantom = crossed(feats, *_square_outline(240, 40, 340, 140))
    assert part.mean() <= OBJECT_CROSSED_RATE
    # Each cell's crossing line falls within a few pixels of one sample in
    # about every CELL_PX / step samples: a share of a fifth or more.
    assert phantom.mean() > 0.15


def test_the_chance_rate_follows_the_background():
    """A checkerboard's edges are crossed at every cell corner; a lone
    square's on a plain background nowhere (its corners are ends, not
    crossings)."""
    grid = chance_crossed_rate(extract_features(_checkerboard()))
    plain = np.full((300, 400), 90, np.uint8)
    plain[100:200, 150:260] = 200
    lone = chance_crossed_rate(extract_features(plain))
    assert grid > 0.08
    assert lone < 0.02
    assert chance_crossed_rate(extract_features(np.full((50, 60), 90, np.uint8))) == 0.0


@settings(max_examples=200, deadline=None)
@given(st.floats(0.0, 1.0))
def test_the_ratios_are_of_two_proper_distributions(chance_rate):
    """Weighted by the clutter's probabilities of crossed and not crossed,
    the ratios give the part's, which sum to one; a crossing never counts
    for the part and is neutral where the image's lines seldom cross."""
    crossed_llr, not_crossed_llr = crossing_log_ratios(chance_rate)
    p_clutter = min(max(chance_rate, OBJECT_CROSSED_RATE), 0.95)
    total = p_clutter * np.exp(crossed_llr) + (1 - p_clutter) * np.exp(not_crossed_llr)
    assert abs(total - 1.0) < 1e-9
    assert crossed_llr <= 0.0 <= not_crossed_llr
    if chance_rate <= OBJECT_CROSSED_RATE:
        assert crossed_llr == 0.0 == not_crossed_llr


def test_the_evidence_ranks_the_part_above_the_phantom_and_is_zero_on_plain_ground():
    feats = _part_on_checkerboard()
    rate = chance_crossed_rate(feats)
    part_uv, part_tangent = _square_outline(107, 87, 193, 173)
    phantom_uv, phantom_tangent = _square_outline(240, 40, 340, 140)
    n = min(len(part_uv), len(phantom_uv))
    uv = np.stack([part_uv[:n], phantom_uv[:n]])
    tangent = np.stack([part_tangent[:n], phantom_tangent[:n]])
    everywhere = np.ones((2, n), bool)
    part, phantom = crossing_evidence(feats, uv, tangent, everywhere, everywhere, rate)
    assert part > 0.0 > phantom
    # Samples that found no edge are not judged.
    nothing = crossing_evidence(feats, uv, tangent, ~everywhere, everywhere, rate)
    np.testing.assert_array_equal(nothing, 0.0)
    plain = np.full((300, 400), 90, np.uint8)
    plain[87:174, 107:194] = 200
    plain_feats = extract_features(plain)
    np.testing.assert_array_equal(
        crossing_evidence(plain_feats, uv, tangent, everywhere, everywhere,
                          chance_crossed_rate(plain_feats)), 0.0)
