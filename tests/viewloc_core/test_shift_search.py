"""The compiled shift search of the refinement against its array form."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from viewloc_core.shift_search import shift_grid, shift_scores


def _array_form(grad, uv, normal, rad, cap):
    """The search as it was written with cv2.remap over every shifted point."""
    grid = np.arange(-rad, rad + 1, dtype=np.float64)
    dy, dx = np.meshgrid(grid, grid, indexing="ij")
    shifts = np.column_stack([dx.ravel(), dy.ravel()])
    sample_map = (uv[None, :, :] + shifts[:, None, :]).astype(np.float32)
    planes = [np.ascontiguousarray(grad[..., k]) for k in range(2)]
    samples = [cv2.remap(p, sample_map, None, cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0) for p in planes]
    along = np.abs(samples[0] * normal[:, 0] + samples[1] * normal[:, 1])
    return np.minimum(along, cap).sum(axis=1, dtype=np.float64)


@pytest.mark.parametrize("seed", range(4))
def test_equals_the_array_form(seed: int) -> None:
    rng = np.random.default_rng(seed)
    h, w = 40, 56
    grad = rng.normal(0.0, 0.05, (h, w, 2)).astype(np.float32)
    # Points anywhere, some so near the border that shifts leave the image.
    uv = rng.uniform([-2.0, -2.0], [w + 1.0, h + 1.0], (60, 2))
    angle = rng.uniform(0, 2 * np.pi, 60)
    normal = np.column_stack([np.cos(angle), np.sin(angle)])
    rad = int(rng.integers(1, 9))
    cap = 0.08
    got = shift_scores(grad, uv, normal, rad, cap)
    np.testing.assert_allclose(got, _array_form(grad, uv, normal, rad, cap),
                               rtol=1e-5, atol=1e-6)


def test_a_shifted_outline_is_found_at_its_shift() -> None:
    # A bright disc; contour points on a circle 3 px left and 2 px above it.
    h, w = 80, 100
    yy, xx = np.mgrid[0:h, 0:w]
    image = (np.hypot(xx - 50.0, yy - 40.0) < 20.0).astype(np.float32)
    image = cv2.GaussianBlur(image, (0, 0), 1.0)
    grad = np.dstack([cv2.Sobel(image, cv2.CV_32F, 1, 0) / 8,
                      cv2.Sobel(image, cv2.CV_32F, 0, 1) / 8]).astype(np.float32)
    angle = np.linspace(0, 2 * np.pi, 90, endpoint=False)
    normal = np.column_stack([np.cos(angle), np.sin(angle)])
    uv = np.array([47.0, 38.0]) + 20.0 * normal
    rad = 6
    scores = shift_scores(grad, uv, normal, rad, 1.0)
    best = int(np.argmax(scores))
    side = 2 * rad + 1
    assert (best % side - rad, best // side - rad) == (3, 2)
    # Saturation: no point adds more than the cap.
    assert shift_scores(grad, uv, normal, rad, 0.01).max() <= 90 * 0.01 + 1e-6


def test_outside_the_image_reads_zero() -> None:
    grad = np.ones((10, 10, 2), np.float32)
    far = np.array([[-30.0, -30.0]])
    assert shift_scores(grad, far, np.array([[1.0, 0.0]]), 3, 10.0).max() == 0.0


@pytest.mark.parametrize("rad", [1, 3, 8])
def test_the_grid_lists_the_shifts_in_the_kernels_order(rad: int) -> None:
    # One bright pixel under a single contour point: the shift that moves
    # the point onto it scores highest, and the grid names that shift.
    shifts, dist2 = shift_grid(rad)
    side = 2 * rad + 1
    assert shifts.shape == (side * side, 2)
    assert tuple(shifts[len(shifts) // 2]) == (0.0, 0.0)
    np.testing.assert_array_equal(dist2, (shifts.astype(np.float64) ** 2).sum(axis=1))
    grad = np.zeros((40, 40, 2), np.float32)
    for target in [(rad, -rad), (-rad, 0), (1 - rad, rad)]:
        grad[:] = 0.0
        grad[20 + target[1], 20 + target[0], 0] = 1.0
        scores = shift_scores(grad, np.array([[20.0, 20.0]]), np.array([[1.0, 0.0]]), rad, 10.0)
        assert tuple(shifts[int(np.argmax(scores))]) == target
