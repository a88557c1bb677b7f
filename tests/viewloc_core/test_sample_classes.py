"""Classes of the training views' edge samples: outline, crease, interior."""

from dataclasses import replace

import cv2
import numpy as np

from viewloc_core.edge_evidence import (
    SAMPLE_ANY,
    SAMPLE_CREASE,
    SAMPLE_INTERIOR,
    SAMPLE_OUTLINE,
)
from viewloc_core.features import ORIENTATION_BINS
from viewloc_core.sample_classes import sample_codes, training_view_sample_classes
from viewloc_core.view_search import build_templates


def _silhouette_distance(model, t: int) -> np.ndarray:
    """Distance (px) of every training-view pixel to the boundary of the
    mesh's silhouette in view ``t``, from the triangles projected and filled
    (independent of the contour model)."""
    size = model.train_size_px
    centre = (size - 1) / 2.0
    verts = (np.asarray(model.mesh_vertices_mm, np.float64) - model.origin_offset_mm)
    cam = verts @ model.training.R_m2c[t].T + [0.0, 0.0, model.d0_mm]
    uv = model.f_train_px * cam[:, :2] / cam[:, 2:3] + centre
    scale = 8  # sub-pixel fill
    mask = np.zeros((size * scale, size * scale), np.uint8)
    tris = np.rint((uv[np.asarray(model.mesh_faces)] + 0.5) * scale - 0.5).astype(np.int32)
    for tri in tris:  # one by one: fillPoly's scanlines cancel where polygons overlap
        cv2.fillConvexPoly(mask, tri, 255)
    mask = cv2.resize(mask, (size, size), interpolation=cv2.INTER_AREA) >= 128
    boundary = (mask ^ cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool))
    return cv2.distanceTransform((~boundary).astype(np.uint8), cv2.DIST_L2, 5)


def test_outline_samples_lie_on_the_silhouette_and_interior_ones_inside(bracket_model):
    templates = build_templates(bracket_model)
    classes = templates.bins8 // ORIENTATION_BINS
    centre = (bracket_model.train_size_px - 1) / 2.0
    near_outline, near_other = [], []
    for t in range(len(templates)):
        dist = _silhouette_distance(bracket_model, t)
        ok = templates.valid[t]
        ij = np.rint(templates.pts[t, ok] + centre).astype(int)
        d = dist[ij[:, 1].clip(0, dist.shape[0] - 1), ij[:, 0].clip(0, dist.shape[1] - 1)]
        near_outline.append(d[classes[t, ok] == SAMPLE_OUTLINE])
        near_other.append(d[np.isin(classes[t, ok], (SAMPLE_INTERIOR, SAMPLE_CREASE))])
    outline, other = np.concatenate(near_outline), np.concatenate(near_other)
    # Every real sample is classified, and the bracket shows all three kinds.
    assert not np.any(classes[templates.valid] == SAMPLE_ANY)
    assert len(outline) > len(other) > 0
    assert np.any(classes == SAMPLE_CREASE)
    # Outline samples are on the silhouette's boundary, the others inside it.
    assert np.median(outline) <= 1.0 and np.percentile(outline, 95) <= 3.0
    assert np.median(other) >= 3.0


def test_padding_and_models_without_contours_stay_unclassified(bracket_model):
    templates = build_templates(bracket_model)
    assert np.all(templates.bins8[~templates.valid] == 0)
    counts = templates.valid.sum(axis=1)
    without = training_view_sample_classes(replace(bracket_model, contour=None),
                                           templates.pts, counts)
    assert np.all(without == SAMPLE_ANY)


def test_sample_codes_carry_the_bin_and_the_class():
    bins = np.arange(ORIENTATION_BINS).repeat(4).reshape(-1, 4)
    classes = np.tile([SAMPLE_ANY, SAMPLE_OUTLINE, SAMPLE_INTERIOR, SAMPLE_CREASE],
                      (ORIENTATION_BINS, 1))
    codes = sample_codes(bins, classes)
    assert codes.dtype == np.uint8
    np.testing.assert_array_equal(codes % ORIENTATION_BINS, bins)
    np.testing.assert_array_equal(codes // ORIENTATION_BINS, classes)
