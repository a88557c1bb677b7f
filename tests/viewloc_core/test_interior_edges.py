"""Interior edges: the edges inside a silhouette that a pose's contour does not explain."""

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from viewloc_core.interior_edges import InteriorEdges, interior_edges

SHAPE = (200, 240)
CENTRE = (120.0, 100.0)


def _disc_samples(radius: float, spacing: float = 2.0) -> np.ndarray:
    """Surface sample pixels (N, 2) filling a disc about CENTRE."""
    xs = np.arange(-radius, radius + 1e-9, spacing)
    xx, yy = np.meshgrid(xs, xs)
    keep = xx ** 2 + yy ** 2 <= radius ** 2
    return np.stack([xx[keep] + CENTRE[0], yy[keep] + CENTRE[1]], axis=1)


def _circle(radius: float, n: int = 400) -> np.ndarray:
    """Points (n, 2) on a circle about CENTRE."""
    a = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    return np.stack([CENTRE[0] + radius * np.cos(a), CENTRE[1] + radius * np.sin(a)], axis=1)


def _edge_distance(*radii: float, shape: tuple[int, int] = SHAPE, scale: float = 1.0
                   ) -> np.ndarray:
    """Distance map of an edge image with one-pixel circles of ``radii`` (full
    resolution) drawn at ``scale`` level pixels per pixel."""
    edges = np.zeros(shape, np.uint8)
    for r in radii:
        cv2.circle(edges, (round((CENTRE[0] + 0.5) * scale - 0.5),
                           round((CENTRE[1] + 0.5) * scale - 0.5)),
                   round(r * scale), 255, 1)
    return cv2.distanceTransform(np.where(edges > 0, 0, 1).astype(np.uint8), cv2.DIST_L2,
                                 cv2.DIST_MASK_5)


def test_an_inner_circle_the_contour_predicts_is_explained():
    # A disc of radius 40 with an inner rim of radius 20 in the image.
    distance = _edge_distance(40.0, 20.0)
    surface = _disc_samples(40.0)
    both = interior_edges(distance, 1.0, surface, 2.0, np.vstack([_circle(40.0), _circle(20.0)]))
    outline_only = interior_edges(distance, 1.0, surface, 2.0, _circle(40.0))
    assert both.unexplained == 0
    # The rim is about 2 pi 20 = 126 pixels long; the outline explains none of it.
    assert 100 <= outline_only.unexplained <= 160
    assert outline_only.explained_share < both.explained_share == pytest.approx(1.0)


def test_the_outline_and_edges_outside_do_not_count():
    # Edges on the silhouette's border (its own outline) and a circle around it.
    distance = _edge_distance(40.0, 60.0)
    result = interior_edges(distance, 1.0, _disc_samples(40.0), 2.0, np.empty((0, 2)))
    assert result.unexplained == 0
    assert result.predicted == 0
    assert result.explained_share == 1.0


def test_counts_are_made_at_the_level_of_the_edge_map():
    # The same scene with the edge map at half resolution: half the pixels of rim.
    full = interior_edges(_edge_distance(40.0, 20.0), 1.0, _disc_samples(40.0), 2.0,
                          _circle(40.0))
    half_shape = (SHAPE[0] // 2, SHAPE[1] // 2)
    half = interior_edges(_edge_distance(40.0, 20.0, shape=half_shape, scale=0.5), 0.5,
                          _disc_samples(40.0), 2.0, _circle(40.0))
    assert half.unexplained == pytest.approx(full.unexplained / 2, rel=0.3)
    assert half.predicted == pytest.approx(full.predicted / 2, rel=0.3)


def test_no_surface_in_the_image_gives_nothing():
    distance = _edge_distance(20.0)
    nothing = InteriorEdges(0, 0)
    assert interior_edges(distance, 1.0, np.empty((0, 2)), 2.0, _circle(20.0)) == nothing
    far = _disc_samples(10.0) + 1000.0
    assert interior_edges(distance, 1.0, far, 2.0, _circle(20.0)) == nothing


@settings(max_examples=40, deadline=None)
@given(shift=st.tuples(st.floats(-150, 150), st.floats(-150, 150)),
       radius=st.floats(3.0, 60.0))
def test_counts_are_bounded_by_the_pixels_inside(shift, radius):
    # Wherever the part lies (partly or wholly outside the image), the
    # unexplained edge pixels are no more than the edge pixels of the image
    # and the share is in [0, 1].
    distance = _edge_distance(40.0, 20.0, 30.0)
    surface = _disc_samples(radius) + np.array(shift)
    result = interior_edges(distance, 1.0, surface, 2.0, _circle(radius) + np.array(shift))
    assert 0 <= result.unexplained <= int(np.count_nonzero(distance < 0.5))
    assert 0.0 <= result.explained_share <= 1.0
