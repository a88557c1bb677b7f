"""U-junctions: three sides of a shape as one feature, similarity-invariant."""

import math

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from viewloc_core.features import (
    KIND_U_JUNCTION,
    FeatureConfig,
    _junctions,
    extract_features,
)
from viewloc_core.u_junctions import u_junctions


def _u_of(segments: np.ndarray):
    seg = np.asarray(segments, np.float32)
    _, meeting_ends, vertex = _junctions(seg, FeatureConfig())
    return u_junctions(seg, meeting_ends, vertex)


def _rectangle(w: float, h: float) -> np.ndarray:
    # Sides with small gaps at the corners, as LSD leaves them, and in no
    # particular direction.
    return np.array([[2, 0, w - 2, 0], [w, h - 2, w, 2], [w - 2, h, 2, h], [0, 2, 0, h - 2]],
                    np.float32) + 100.0


def test_each_side_of_a_rectangle_is_the_base_of_one_u():
    xy, theta, scale, attrs = _u_of(_rectangle(80.0, 40.0))
    assert len(xy) == 4
    assert sorted(np.round(scale).tolist()) == [40, 40, 80, 80]
    # Right angles at both corners: mean 90 deg, no difference.
    assert np.allclose(attrs[:, 0], math.pi / 2, atol=1e-3)
    assert np.allclose(attrs[:, 1], 0.0, atol=1e-3)
    # Each sits mid-side and points into the rectangle (towards its centre).
    centre = np.array([140.0, 120.0])
    inward = centre - xy
    direction = np.stack([np.cos(theta), np.sin(theta)], axis=1)
    assert np.all((inward * direction).sum(axis=1) > 0.99 * np.linalg.norm(inward, axis=1))


def test_arms_on_opposite_sides_make_no_u():
    zigzag = np.array([[0, 0, 0, 40], [2, 42, 60, 42], [62, 44, 62, 90]], np.float32) + 50.0
    assert len(_u_of(zigzag)[0]) == 0
    cup = np.array([[0, 0, 0, 40], [2, 42, 60, 42], [62, 40, 62, 0]], np.float32) + 50.0
    assert len(_u_of(cup)[0]) == 1


@settings(max_examples=60, deadline=None)
@given(angle=st.floats(-math.pi, math.pi), scale=st.floats(0.5, 3.0),
       shift=st.tuples(st.floats(-50, 50), st.floats(-50, 50)),
       skew=st.floats(-0.5, 0.5))
def test_u_junctions_follow_a_similarity(angle, scale, shift, skew):
    # A trapezoid-like cup: unequal angles, so both attributes are non-trivial.
    cup = np.array([[0, 0, 30 * skew, 40], [30 * skew + 2, 42, 60, 42], [62, 40, 70, 0]],
                   np.float64)
    c, s = math.cos(angle), math.sin(angle)
    R = np.array([[c, -s], [s, c]])

    def moved(seg: np.ndarray) -> np.ndarray:
        pts = seg.reshape(-1, 2) @ (scale * R).T + np.asarray(shift) + 300.0
        return pts.reshape(-1, 4)

    base = _u_of(cup + 300.0)
    turned = _u_of(moved(cup))
    assert len(base[0]) == len(turned[0]) == 1
    expected_xy = (base[0].astype(np.float64) - 300.0) @ (scale * R).T + np.asarray(shift) + 300.0
    assert np.allclose(turned[0], expected_xy, atol=1e-2 * scale + 1e-2)
    dtheta = (turned[1][0] - base[1][0] - angle + math.pi) % (2 * math.pi) - math.pi
    assert abs(dtheta) < 1e-3
    assert turned[2][0] == pytest.approx(scale * base[2][0], rel=1e-4)
    assert np.allclose(turned[3], base[3], atol=1e-3)


def test_a_drawn_box_gives_u_junctions_whatever_its_contrast():
    found = []
    for fg, bg in ((200, 40), (40, 200)):
        img = np.full((240, 320), bg, np.uint8)
        cv2.rectangle(img, (90, 70), (230, 160), fg, -1)
        g = extract_features(img).grouped
        u = g.kind == KIND_U_JUNCTION
        found.append(sorted(np.round(g.scale[u] / 10).tolist()))
    assert len(found[0]) == 4 and found[0] == found[1]


def test_clutter_density_of_u_attributes_matches_uniform_angles():
    # Two independent opening angles, uniform over the accepted range: the
    # density the alignment weighs U-junction pairings against.
    from viewloc_core.align import _log_background_density

    lo = math.radians(FeatureConfig().min_junction_angle_deg)
    rng = np.random.default_rng(0)
    a1, a2 = rng.uniform(lo, math.pi - lo, (2, 200_000))
    attrs = np.stack([(a1 + a2) / 2, np.abs(a1 - a2) / 2], axis=1)
    # Empirical density in a small box around a few points inside the region.
    for centre in ((1.2, 0.2), (1.6, 0.5), (2.0, 0.1)):
        half = 0.05
        inside = np.all(np.abs(attrs - centre) < half, axis=1).mean() / (2 * half) ** 2
        expected = math.exp(_log_background_density(KIND_U_JUNCTION, np.array([centre]))[0])
        assert inside == pytest.approx(expected, rel=0.05)
