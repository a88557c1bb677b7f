"""The compiled search along contour normals: equal to its array form (cv2.remap
sampling) bit for bit, and finds a known edge where it is."""

from __future__ import annotations

import cv2
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from viewloc_core.normal_search import search_normals


def _prior(search: int) -> np.ndarray:
    ks = np.arange(-search + 1, search, dtype=np.float64)
    return np.exp(-0.5 * (ks / max(1.0, search / 3.0)) ** 2)


def _search_by_arrays(grad, uv, normal, search, min_gradient, cos_max):
    """The array formulation the kernel replaced: one cv2.remap of a (K, N)
    sample map, then elementwise steps over (K, N) in float32."""
    ks = np.arange(-search, search + 1, dtype=np.float32).reshape(-1, 1, 1)
    n32 = normal.astype(np.float32)
    n = len(uv)
    sample_map = ks * n32
    sample_map += uv.astype(np.float32)
    g = cv2.remap(grad, sample_map, None, cv2.INTER_LINEAR,  # type: ignore[call-overload]
                  borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    products = g * n32
    along = np.abs(products[..., 0] + products[..., 1])
    np.multiply(g, g, out=products)
    limit = (products[..., 0] + products[..., 1]) * np.float32(cos_max * cos_max)
    edge = (along >= np.float32(min_gradient)) & (along * along >= limit)
    score = np.where(edge, along, np.float32(0.0))
    mid = score[1:-1]
    peak = (mid >= np.maximum(score[:-2], score[2:])) & (mid > 0)
    weighted = np.zeros(mid.shape)
    np.multiply(mid, _prior(search)[:, None], out=weighted, where=peak)
    inner = weighted.argmax(axis=0)
    found = peak.any(axis=0)
    cols = np.arange(n)
    left, s0, right = (along[inner + d, cols].astype(np.float64) for d in (0, 1, 2))
    denom = left - 2.0 * s0 + right
    sub = np.zeros(n)
    safe = np.abs(denom) > 1e-12
    np.divide(0.5 * (left - right), denom, out=sub, where=safe)
    return found, inner + (1 - search) + np.clip(sub, -0.5, 0.5)


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    height=st.integers(4, 60), width=st.integers(4, 60),
    n_points=st.integers(1, 80), search=st.integers(1, 9),
    min_gradient=st.floats(0.0, 0.05), max_angle_deg=st.floats(5.0, 85.0),
    on_grid=st.booleans(),
)
def test_equals_the_array_form_bit_for_bit(seed, height, width, n_points, search, min_gradient,
                                           max_angle_deg, on_grid):
    rng = np.random.default_rng(seed)
    grad = rng.normal(0.0, 0.1, (height, width, 2)).astype(np.float32)
    grad = np.ascontiguousarray(cv2.GaussianBlur(grad, (0, 0), 1.0))
    # Points inside, near the border and outside the image.
    uv = np.column_stack([rng.uniform(-12, width + 12, n_points),
                          rng.uniform(-12, height + 12, n_points)])
    if on_grid:  # on OpenCV's 1/32 px grid and half-way between its nodes
        uv = np.round(uv * 64.0) / 64.0
    angle = rng.uniform(0.0, 2.0 * np.pi, n_points)
    normal = np.column_stack([np.cos(angle), np.sin(angle)])
    cos_max = float(np.cos(np.radians(max_angle_deg)))
    found, offset = search_normals(grad, uv, normal, search, min_gradient, cos_max,
                                   _prior(search))
    found_ref, offset_ref = _search_by_arrays(grad, uv, normal, search, min_gradient, cos_max)
    np.testing.assert_array_equal(found, found_ref)
    np.testing.assert_array_equal(offset, offset_ref)


def test_finds_a_vertical_edge_at_its_sub_pixel_offset():
    # A smooth step at x = 20.3: the gradient peaks there, along +x.
    xs = np.arange(40, dtype=np.float64)
    column = 1.0 / (1.0 + np.exp(-(xs - 20.3) / 0.8))
    gx = np.gradient(column)
    grad = np.zeros((30, 40, 2), np.float32)
    grad[..., 0] = gx[None, :]
    # Points left of the edge with normals along x and along -x (sign-agnostic);
    # one with a normal along y sees no edge (gradient at 90 degrees).
    uv = np.array([[17.0, 10.0], [23.5, 12.0], [19.0, 15.0]])
    normal = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0]])
    found, offset = search_normals(grad, uv, normal, 6, 0.01, np.cos(np.radians(35.0)),
                                   _prior(6))
    assert list(found) == [True, True, False]
    assert abs(offset[0] - 3.3) < 0.1
    assert abs(offset[1] - 3.2) < 0.1


def test_an_edge_at_the_end_of_the_line_is_not_taken():
    # The strongest response lies beyond the line: its last sample is only
    # the slope, not a maximum.
    xs = np.arange(40, dtype=np.float64)
    grad = np.zeros((20, 40, 2), np.float32)
    grad[..., 0] = np.exp(-0.5 * ((xs - 30.0) / 1.5) ** 2)[None, :]
    found, _ = search_normals(grad, np.array([[20.0, 10.0]]), np.array([[1.0, 0.0]]), 5, 0.01,
                              0.5, _prior(5))
    assert not found[0]
