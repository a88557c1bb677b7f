"""Image edges inside a fitted part that its pose does not predict.

The refinement's inlier fraction asks one way round: of the contour a pose
predicts (outline and creases), how much finds an image edge. Two poses
with the same outline answer it alike, and the one that predicts fewer
creases answers it better: a knob seen from behind shows only its outline,
all of it confirmed, while the true pose predicts the inner rim of its dish
as well, some of which the light does not show (novel bench set, knob: the
reversed pose confirmed 0.95 of its contour, the true one 0.84). The other
way round tells them apart: the image has a strong circular edge inside the
outline, which the true pose explains and the reversed one does not.

This module counts, at the pyramid level the features were found on, the
image's edge pixels inside the pose's silhouette (away from its outline)
that no predicted contour point lies near, against the predicted contour's
own length in the same pixels. Edges that no pose predicts (a texture, a
reflection, a shadow across the part) count against every rival at one
location alike, so the count is a comparison between fits of one place,
not a test of one fit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from viewloc_core.shading import points_mask, silhouette_mask

#: An image edge pixel this close (level pixels) to a predicted contour
#: point is explained by it: the pose's error and the level's blur.
EXPLAINED_PX = 2.0

#: Pixels of the silhouette this close (level pixels) to its border are not
#: inside: the outline's own edge lies there, blurred.
BORDER_PX = 2


@dataclass(frozen=True, slots=True)
class InteriorEdges:
    """The edge pixels inside a fitted part's silhouette, at the search level.

    Attributes
    ----------
    unexplained : int
        Image edge pixels inside the silhouette (at least ``BORDER_PX`` from
        its border) farther than ``EXPLAINED_PX`` from every predicted
        contour point.
    predicted : int
        Level pixels the predicted contour points fall on (its length there).
    """

    unexplained: int
    predicted: int

    @property
    def explained_share(self) -> float:
        """``predicted / (predicted + unexplained)`` in [0, 1]: 1 when every
        edge inside is one the pose predicts (1 when there is nothing)."""
        total = self.predicted + self.unexplained
        return self.predicted / total if total > 0 else 1.0


def interior_edges(
    edge_distance: NDArray[np.float32], factor: float, surface_uv: NDArray[np.floating],
    dot_px: float, contour_uv: NDArray[np.floating],
) -> InteriorEdges:
    """Count the image edges inside a silhouette that the contour does not explain.

    Parameters
    ----------
    edge_distance : (h, w) float32
        Distance of each pixel of the search level to its nearest edge pixel
        (:attr:`viewloc_core.features.ImageFeatures.edge_distance`; 0 on edges).
    factor : float
        Level pixels per full-resolution pixel.
    surface_uv : (S, 2) array
        Full-resolution pixels of the part's visible surface samples
        (:func:`viewloc_core.shading.visible_samples`).
    dot_px : float
        Their spacing in full-resolution pixels: discs that wide join into
        the silhouette.
    contour_uv : (C, 2) array
        Full-resolution pixels of the pose's predicted contour points, every
        kind (:func:`viewloc_core.refine.project_contour_view`).

    Returns
    -------
    InteriorEdges
        Zero counts when no surface sample falls inside the level.
    """
    h, w = edge_distance.shape
    dot = max(1, round(dot_px * factor))
    margin = dot + BORDER_PX + 1
    surf = (np.asarray(surface_uv, np.float64) + 0.5) * factor - 0.5
    cont = (np.asarray(contour_uv, np.float64).reshape(-1, 2) + 0.5) * factor - 0.5
    if len(surf) == 0:
        return InteriorEdges(0, 0)
    x0 = max(0, math.floor(float(surf[:, 0].min())) - margin)
    y0 = max(0, math.floor(float(surf[:, 1].min())) - margin)
    x1 = min(w, math.ceil(float(surf[:, 0].max())) + margin + 1)
    y1 = min(h, math.ceil(float(surf[:, 1].max())) + margin + 1)
    if x0 >= x1 or y0 >= y1:
        return InteriorEdges(0, 0)
    shape = (y1 - y0, x1 - x0)
    silhouette = silhouette_mask(surf, x0, y0, shape, dot)
    # The dilation reaches dot beyond the outline; the erosion takes that
    # back and the outline's own blurred edge with it.
    inside = cv2.erode(silhouette, cv2.getStructuringElement(
        cv2.MORPH_ELLIPSE, (2 * margin - 1, 2 * margin - 1))).astype(bool)
    contour = points_mask(cont, x0, y0, shape)
    predicted = int(np.count_nonzero(contour))
    if not inside.any():
        return InteriorEdges(0, predicted)
    if predicted:
        far = cv2.distanceTransform(1 - contour, cv2.DIST_L2, cv2.DIST_MASK_5) > EXPLAINED_PX
    else:
        far = np.ones(shape, bool)
    on_edge = edge_distance[y0:y1, x0:x1] < 0.5
    return InteriorEdges(int(np.count_nonzero(on_edge & inside & far)), predicted)

