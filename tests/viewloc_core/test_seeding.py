"""Seeds of the alignment: the compiled kernel against the array formulation."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from viewloc_core import similarity as sim2
from viewloc_core.seeding import seed_similarities


def _array_seeds(img_xy, img_theta, img_scale, m_xy, m_theta, m_scale, parallel, k, j,
                 min_scale, max_scale):
    """The array formulation align._seeds used before it was compiled."""
    angle = img_theta[k].astype(np.float64) - m_theta[j]
    scale = img_scale[k].astype(np.float64) / m_scale[j]
    par = parallel[j]
    src = np.concatenate([np.arange(len(k)), np.flatnonzero(par)])
    k2, j2 = k[src], j[src]
    angle = np.concatenate([angle, angle[par] + np.pi])
    scale = np.concatenate([scale, scale[par]])
    c, s = scale * np.cos(angle), scale * np.sin(angle)
    mx, my = m_xy[j2, 0], m_xy[j2, 1]
    ix, iy = img_xy[k2, 0].astype(np.float64), img_xy[k2, 1].astype(np.float64)
    sims = np.stack([ix - (c * mx - s * my), iy - (s * mx + c * my), sim2.wrap_angle(angle),
                     scale], axis=1)
    ok = (scale >= min_scale) & (scale <= max_scale)
    return sims[ok], src[ok]


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(0, 400))
def test_compiled_seeds_equal_the_array_formulation(seed, n_pairings):
    rng = np.random.default_rng(seed)
    n_img, n_model = 30, 50
    img_xy = rng.uniform(0, 400, (n_img, 2)).astype(np.float32)
    img_theta = rng.uniform(0, 2 * np.pi, n_img).astype(np.float32)
    img_scale = rng.uniform(2, 80, n_img).astype(np.float32)
    m_xy = rng.uniform(-60, 60, (n_model, 2))
    m_theta = rng.uniform(0, 2 * np.pi, n_model)
    m_scale = rng.uniform(2, 80, n_model)
    parallel = rng.random(n_model) < 0.3
    k = rng.integers(0, n_img, n_pairings)
    j = rng.integers(0, n_model, n_pairings)
    want_sims, want_src = _array_seeds(img_xy, img_theta, img_scale, m_xy, m_theta, m_scale,
                                       parallel, k, j, 0.3, 3.0)
    sims, src = seed_similarities(img_xy, img_theta, img_scale, m_xy, m_theta, m_scale,
                                  parallel, k, j, 0.3, 3.0)
    np.testing.assert_array_equal(src, want_src)
    np.testing.assert_allclose(sims, want_sims, rtol=1e-12, atol=1e-9)


def test_a_seed_maps_the_model_feature_onto_the_image_feature():
    """The implied similarity carries the model feature's position onto the
    image feature's, with the angle and scale between them."""
    img_xy = np.array([[210.0, 95.0]], np.float32)
    sims, src = seed_similarities(
        img_xy, np.array([1.2], np.float32), np.array([30.0], np.float32),
        np.array([[12.0, -7.0]]), np.array([0.4]), np.array([20.0]), np.array([True]),
        np.array([0]), np.array([0]), 0.3, 3.0)
    assert list(src) == [0, 0]
    for sim, turn in zip(sims, (0.0, np.pi), strict=True):
        assert np.isclose(sim[3], 1.5)
        assert np.isclose(sim2.wrap_angle(sim[2] - (float(np.float32(1.2)) - 0.4) - turn), 0.0)
        np.testing.assert_allclose(sim2.apply(sim, np.array([[12.0, -7.0]]))[0], img_xy[0],
                                   atol=1e-4)
