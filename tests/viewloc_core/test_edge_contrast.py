"""The refinement's edge floor follows the contrast around the part."""

from __future__ import annotations

import numpy as np
import pytest

from viewloc_core.edge_contrast import (
    EDGE_CONTRAST_SHARE,
    LOWEST_MIN_GRADIENT,
    local_min_gradient,
)
from viewloc_core.refine import RefineOptions, prepare_edges

CEILING = RefineOptions().min_gradient


def _square(contrast: float, noise_std: float = 0.0) -> np.ndarray:
    """(200, 200) float32 grey image in [0, 1]: a 60 px square ``contrast``
    brighter than the ground, centred at (100, 100), plus Gaussian noise."""
    image = np.full((200, 200), 0.4, np.float32)
    image[70:130, 70:130] += contrast
    image += np.random.default_rng(0).normal(0.0, noise_std, image.shape).astype(np.float32)
    return np.clip(image, 0.0, 1.0)


def _floor(image: np.ndarray, centre=(100.0, 100.0), radius_px: float = 40.0) -> float:
    return local_min_gradient(prepare_edges(image, 1), centre, radius_px, CEILING)


def test_a_strong_outline_keeps_the_fixed_floor() -> None:
    assert _floor(_square(0.5)) == CEILING


def test_a_faint_outline_lowers_the_floor_in_proportion() -> None:
    # Fog or dim light scale every gradient alike; the floor scales with them.
    faint, fainter = _floor(_square(0.24)), _floor(_square(0.12))
    assert LOWEST_MIN_GRADIENT < fainter < faint < CEILING
    assert faint / fainter == pytest.approx(2.0, rel=0.05)
    # The floor is a share of the outline's own gradient, under its peak.
    peak = float(np.abs(np.gradient(_square(0.24)[100].astype(np.float64))).max())
    assert faint == pytest.approx(EDGE_CONTRAST_SHARE * peak, rel=0.5)
    assert faint < 0.5 * peak


def test_the_floor_never_drops_below_the_quantisation_step() -> None:
    assert _floor(_square(0.04)) == LOWEST_MIN_GRADIENT
    assert _floor(np.full((200, 200), 0.4, np.float32)) == LOWEST_MIN_GRADIENT


def test_noise_keeps_the_floor_above_its_gradients() -> None:
    # Sensor noise as strong as a faint outline's share: the floor stays
    # above the window's typical gradient, so noise is not taken for edges.
    clean = _floor(_square(0.12))
    noisy_image = _square(0.12, noise_std=0.02)
    noisy = _floor(noisy_image)
    grad = prepare_edges(noisy_image, 1).gradients[0][60:141, 60:141]
    typical = float(np.median(np.hypot(grad[..., 0], grad[..., 1])))
    assert noisy > clean
    assert noisy >= typical * 0.9


@pytest.mark.parametrize("centre", [(-80.0, 100.0), (100.0, 400.0)])
def test_a_window_outside_the_image_keeps_the_fixed_floor(centre) -> None:
    assert _floor(_square(0.04), centre=centre) == CEILING
