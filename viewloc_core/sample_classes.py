"""Which kind of edge each edge sample of a training view stands for.

The view search's templates (:mod:`viewloc_core.view_search`) are the edge
samples of the rendered training views: the part's outline, its creases,
and edges of shading and colour inside it. At the true pose an image finds
them at very different rates (:data:`viewloc_core.edge_evidence.SAMPLE_HIT_RATES`):
the outline nearly always, the inside as the light and the surface's colours
allow. Pope & Lowe give each model feature its own probability of being
detected; here each sample gets that of its class.

The class is read off the part's contour model
(:mod:`viewloc_core.contour_model`), the same geometry the refinement fits:
the view's occluding contour and creases are projected into the training
view, and a sample closer than :data:`CLASS_REACH_PX` to the former is outline,
else closer than that to the latter a crease, else interior (inner occluding
contours included: like shading, they are edges only where the part's two
sides differ in brightness). Models without a contour model (learned from
photos) keep every sample unclassified
(:data:`viewloc_core.edge_evidence.SAMPLE_ANY`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from viewloc_core.camera import Camera
from viewloc_core.contour_model import KIND_CREASE, KIND_OCCLUDING, ContourModel
from viewloc_core.edge_evidence import (
    SAMPLE_ANY,
    SAMPLE_CREASE,
    SAMPLE_INTERIOR,
    SAMPLE_OUTLINE,
)
from viewloc_core.features import ORIENTATION_BINS
from viewloc_core.model import ObjectModel
from viewloc_core.pose import Pose
from viewloc_core.refine import project_contour_view

#: Largest distance (training-view pixels, the part about 128 px across) from
#: a projected contour point at which a sample counts as on that contour:
#: the contour points lie a few pixels apart and the rendered edge is found
#: within a pixel of the true one (median distance of the samples nearest
#: the outline about 1 px).
CLASS_REACH_PX = 2.0


def training_view_sample_classes(
    model: ObjectModel, pts_px: NDArray[np.float64], counts: NDArray[np.int64],
) -> NDArray[np.uint8]:
    """The class of every edge sample of every training view.

    Parameters
    ----------
    model : ObjectModel
    pts_px : (T, P, 2) float64
        Edge samples of each training view, its own frame (pixels from the
        image centre), padded.
    counts : (T,) int64
        Real samples of each view (the first ``counts[t]``).

    Returns
    -------
    (T, P) uint8
        :data:`~viewloc_core.edge_evidence.SAMPLE_OUTLINE`, ``SAMPLE_CREASE``
        or ``SAMPLE_INTERIOR``; ``SAMPLE_ANY`` for padding, for views whose
        contour is not seen, and for every sample of a model without a
        contour model.
    """
    classes = np.full(pts_px.shape[:2], SAMPLE_ANY, np.uint8)
    if model.contour is None:
        return classes
    contour = ContourModel.from_arrays(model.contour)
    size = model.train_size_px
    centre = (size - 1) / 2.0
    # The training views' camera: the part's centred frame at d0 straight
    # ahead (the pose pose_from_similarity gives the identity similarity).
    camera = Camera(model.f_train_px, model.f_train_px, centre, centre, size, size)
    at_d0 = np.array([0.0, 0.0, model.d0_mm])
    for t, n in enumerate(counts):
        if n == 0:
            continue
        pose = Pose(model.training.R_m2c[t], at_d0)
        outline = project_contour_view(camera, contour, pose, KIND_OCCLUDING)
        if outline is None:
            continue
        pts = pts_px[t, :n]
        classes[t, :n] = np.where(_distance(outline[0] - centre, pts) < CLASS_REACH_PX,
                                  SAMPLE_OUTLINE, SAMPLE_INTERIOR)
        creases = project_contour_view(camera, contour, pose, KIND_CREASE)
        if creases is not None:
            on_crease = ((classes[t, :n] == SAMPLE_INTERIOR)
                         & (_distance(creases[0] - centre, pts) < CLASS_REACH_PX))
            classes[t, :n][on_crease] = SAMPLE_CREASE
    return classes


def _distance(contour_px: NDArray[np.float64], pts_px: NDArray[np.float64]) -> NDArray[np.float64]:
    """Distance of each of (N, 2) points to the nearest of (M, 2) contour points."""
    return np.asarray(cKDTree(contour_px).query(pts_px)[0], np.float64)


def sample_codes(bins: NDArray[np.integer], classes: NDArray[np.integer]) -> NDArray[np.uint8]:
    """The codes the evidence kernels read (:mod:`viewloc_core.sample_evidence`):
    ``class * ORIENTATION_BINS + bin``, same shape as ``bins``."""
    return (np.asarray(classes, np.int64) * ORIENTATION_BINS
            + np.asarray(bins, np.int64)).astype(np.uint8)
