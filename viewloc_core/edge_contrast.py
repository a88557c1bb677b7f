"""How strong an image edge must be near a part: the refinement's floor, from its surroundings.

The refinement (:mod:`viewloc_core.refine`) takes a gradient as an edge when
it is at least ``RefineOptions.min_gradient`` (intensity per pixel, intensities
in [0, 1]). A fixed floor assumes a contrast: in fog, haze, dim light or with
a grey part on a grey ground, every gradient shrinks by the same factor and
the part's outline falls under it (hard bench set, L-bracket in fog, refined
from the true pose: inlier fractions 0.50-0.55 at 0.02, 0.80-0.86 at 0.005),
while the feature extractor, whose thresholds follow the image's own
gradients, still finds the location. Here the floor follows the contrast
around the part: a share of the strong gradients in a window as large as the
part, capped by the fixed floor, which stays where edges are strong. Within
a location every fit uses one floor, so their inlier fractions compare.
"""

from __future__ import annotations

import numpy as np

from viewloc_core.refine import EdgePyramid

#: The floor is this share of the window's strong gradients. Hard bench set,
#: learning seeds 0/1/2, against the fixed 0.02 (with the noise bound
#: below): AR_MSSD 0.707 -> 0.736 and AR_MSPD 0.745 -> 0.779 in the mean. A
#: share of 0.2 left most floors at 0.02 and gained about half as much at
#: seed 0 (without the noise bound).
EDGE_CONTRAST_SHARE = 0.12

#: The window's strong gradients: this percentile of its gradient
#: magnitudes. A part's outline and creases, 2-3 px wide, cover several %
#: of a square as wide as the part, so this lands on them when the part is
#: there and on the strongest clutter when it is not.
STRONG_GRADIENT_PERCENTILE = 97.0

#: The floor is at least this multiple of the window's median gradient
#: magnitude: the gradient of its sensor noise and texture, which real
#: photos have and renders do not (LM-O photos: image medians 0.014-0.02).
#: LM-O, ape: AR_MSSD/AR_MSPD 0.102/0.159 with the fixed floor, 0.093/0.149
#: without this bound, 0.106/0.165 with it.
NOISE_MULTIPLE = 1.0

#: The floor never goes below this (intensity per pixel): about 1.3 grey
#: levels per pixel of an 8-bit image, the size of its quantisation steps.
LOWEST_MIN_GRADIENT = 0.005


def local_min_gradient(
    edges: EdgePyramid, centre_px: tuple[float, float], radius_px: float, ceiling: float,
) -> float:
    """The weakest gradient taken as an edge for a part near a point.

    Parameters
    ----------
    edges : EdgePyramid
        The scene's gradients; the finest level is read.
    centre_px : (float, float)
        The part's image centre (x, y), full-resolution pixels.
    radius_px : float
        Half the part's image diameter, pixels: the window's half side.
    ceiling : float
        The fixed floor (``RefineOptions.min_gradient``), intensity per pixel;
        never exceeded.

    Returns
    -------
    float
        Intensity per pixel, in ``[min(LOWEST_MIN_GRADIENT, ceiling), ceiling]``;
        ``ceiling`` when the window lies outside the image or is under 4 px wide.
    """
    grad = edges.gradients[0]
    h, w = grad.shape[:2]
    x, y = centre_px
    r = max(float(radius_px), 0.0)
    x0, x1 = max(0, int(x - r)), min(w, int(x + r) + 1)
    y0, y1 = max(0, int(y - r)), min(h, int(y + r) + 1)
    if x1 - x0 < 4 or y1 - y0 < 4:
        return ceiling
    # Every other pixel each way is plenty for a percentile and a quarter
    # of the cost.
    window = grad[y0:y1:2, x0:x1:2].reshape(-1, 2)
    magnitude = np.hypot(window[:, 0], window[:, 1])
    typical, strong = np.percentile(magnitude, [50.0, STRONG_GRADIENT_PERCENTILE])
    return min(ceiling, max(LOWEST_MIN_GRADIENT, NOISE_MULTIPLE * float(typical),
                            EDGE_CONTRAST_SHARE * float(strong)))
