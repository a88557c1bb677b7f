"""The part's colour boundary as an edge of the refinement's gradient pyramid."""

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from tests.viewloc_core.test_refine import CAM, _perturbed
from viewloc_core.colour_edges import COLOUR_EDGE_WEIGHT, with_colour_boundary
from viewloc_core.errors import InvalidInputError
from viewloc_core.pose import Pose, rotation_angle_deg
from viewloc_core.refine import EdgePyramid, prepare_edges, refine_pose


def _vertical_step(height: int, width: int, column: int, low: float, high: float) -> np.ndarray:
    """(height, width) float32: ``high`` left of ``column``, ``low`` from it on."""
    out = np.full((height, width), low, np.float32)
    out[:, :column] = high
    return out


def test_each_pixel_keeps_the_stronger_of_the_image_and_colour_gradients():
    """An image edge at column 4 and a colour step at column 12: each stays
    where it is the stronger, and the input pyramid is left as it was."""
    image = _vertical_step(16, 20, 4, 0.2, 0.8)[..., None].repeat(3, axis=2)
    edges = prepare_edges(image, 2)
    before = [g.copy() for g in edges.gradients]
    posterior = _vertical_step(16, 20, 12, 0.1, 0.9)
    merged = with_colour_boundary(edges, posterior)
    assert [g.shape for g in merged.gradients] == [g.shape for g in edges.gradients]
    assert all(g.dtype == np.float32 for g in merged.gradients)
    assert (merged.width, merged.height) == (edges.width, edges.height)
    for g, b in zip(edges.gradients, before, strict=True):
        assert np.array_equal(g, b)
    level0 = merged.gradients[0]
    # The image's edge (0.6 per pixel across it, Sobel / 8 gives 0.3 at the
    # two columns beside the step) is kept; the colour step (0.8, weighted
    # 0.5: 0.2 at its two columns) appears where the image is flat.
    assert np.allclose(level0[8, 3:5, 0], -0.3, atol=1e-6)
    assert np.allclose(level0[8, 11:13, 0], -COLOUR_EDGE_WEIGHT * 0.4, atol=1e-6)
    assert np.allclose(level0[8, [0, 7, 8, 16, 19], :], 0.0)
    # A weight that makes the colour step the stronger one takes over there.
    heavy = with_colour_boundary(edges, _vertical_step(16, 20, 4, 0.1, 0.9), weight=2.0)
    assert np.allclose(heavy.gradients[0][8, 3:5, 0], -2.0 * 0.4, atol=1e-6)


@settings(max_examples=30, deadline=None)
@given(share=st.floats(0.3, 0.7), factor=st.sampled_from([0.5, 0.625, 1.0, 1.6]))
def test_a_posterior_on_another_grid_keeps_its_step_in_place(share, factor):
    """A posterior on the colour cue's grid (another size than the image's)
    is resampled with pixel centres aligned: its step lands within a pixel
    of where it lies in the image, on the full-resolution level."""
    height, width = 96, 128
    small_w, small_h = round(width * factor), round(height * factor)
    column = max(2, min(small_w - 2, round(share * small_w)))
    posterior = _vertical_step(small_h, small_w, column, 0.0, 1.0)
    flat = EdgePyramid([np.zeros((height, width, 2), np.float32),
                        np.zeros((height // 2, width // 2, 2), np.float32)], width, height)
    merged = with_colour_boundary(flat, posterior)
    strength = np.abs(merged.gradients[0][height // 2, :, 0])
    # The step lies between posterior pixels column - 1 and column, at
    # column - 0.5 on its grid: (x + 0.5) / factor - 0.5 in the image.
    expected = column / (small_w / width) - 0.5
    strongest = np.flatnonzero(strength >= strength.max() - 1e-6)
    assert abs(0.5 * (strongest[0] + strongest[-1]) - expected) <= 1.0


def test_a_bad_posterior_or_weight_is_refused():
    edges = prepare_edges(np.zeros((16, 16), np.uint8), 1)
    with pytest.raises(InvalidInputError) as err:
        with_colour_boundary(edges, np.zeros(16, np.float32))
    assert err.value.field == "posterior"
    with pytest.raises(InvalidInputError) as err:
        with_colour_boundary(edges, np.zeros((16, 16), np.float32), weight=0.0)
    assert err.value.field == "weight"


def _printed_part_on_a_like_table(renderer, prepared, seed: int
                                  ) -> tuple[Pose, np.ndarray, np.ndarray, Pose]:
    """The bracket at a random pose (scipy's uniform rotation of ``seed``),
    barely brighter than the table (4 grey levels), with a bold dark print
    on its face from 6 px inside the outline; the posterior the colour cue
    would give (0.9 on the part, 0.1 off it) on a 400x300 grid; and a start
    4° and 2 % off: (truth, image, posterior, start)."""
    rng = np.random.default_rng(seed)
    truth = Pose(Rotation.random(random_state=seed).as_matrix(),
                 np.array([rng.uniform(-50, 50), rng.uniform(-30, 30), 600.0]))
    mask = renderer.render(prepared, CAM, truth).mask
    image = np.full((CAM.height, CAM.width, 3), 120, np.uint8)
    image[mask] = (124, 120, 118)
    inside = cv2.erode(mask.astype(np.uint8), np.ones((13, 13), np.uint8)).astype(bool)
    stripes = np.broadcast_to((np.arange(CAM.width) // 9) % 2 == 0, mask.shape)
    image[inside & stripes] = (40, 40, 40)
    image = np.clip(image + rng.normal(0, 2, image.shape), 0, 255).astype(np.uint8)
    posterior = cv2.resize(np.where(mask, 0.9, 0.1).astype(np.float32), (400, 300),
                           interpolation=cv2.INTER_AREA)
    return truth, image, posterior, _perturbed(truth, rng, 4.0, 0.02)


@pytest.mark.parametrize("seed", [0, 1, 3])
def test_a_faint_outline_is_fitted_by_the_parts_colour(bracket_contour_scene, seed):
    """A part as bright as the table, with a bold print on its face: on the
    image's edges alone the fit is drawn onto the print (measured 12-32° and
    55-1900 mm off); with the colour boundary it finds the outline (0.35-0.95°,
    0.4-1.9 mm)."""
    renderer, prepared, model = bracket_contour_scene
    truth, image, posterior, start = _printed_part_on_a_like_table(renderer, prepared, seed)
    edges = prepare_edges(image, 2)
    plain = refine_pose(edges, CAM, start, model)
    coloured = refine_pose(with_colour_boundary(edges, posterior), CAM, start, model)
    assert rotation_angle_deg(plain.pose.R_m2c, truth.R_m2c) > 5.0
    assert rotation_angle_deg(coloured.pose.R_m2c, truth.R_m2c) < 1.0
    assert np.linalg.norm(coloured.pose.t_m2c - truth.t_m2c) < 2.5
    assert coloured.inlier_fraction > 0.75
