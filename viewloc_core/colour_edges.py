"""The part's colour boundary as an edge the refinement fits to.

Where the scene's colours tell the part from what lies around it
(:mod:`viewloc_core.part_colour`), the probability that a pixel shows the
part, P(part | colour), steps from high to low across its outline. That
step can be clearer than the outline's intensity edge: a part as bright as
the table shows its outline in colour only, and a print, texture or shading
on its face makes stronger edges just inside the outline, which the
refinement's search along the contour normals may take instead. On the LM-O
photos, with the image's edges alone, 6 of the 18 cat fits at the right
place but wrong in 3D were within 10° and 3-7 % off in depth (every 4th
photo, learning seed 0).

:func:`with_colour_boundary` adds the posterior as one more channel of the
refinement's gradient pyramid, as the colour gradient already takes the
strongest of the image's channels at each pixel
(:func:`viewloc_core.gradient.image_gradient`): a pixel keeps the image's
gradient unless the weighted gradient of the posterior is stronger.

The posterior is read at the image's own resolution
(:meth:`viewloc_core.localize._ColourScene.full_posterior`), the colours'
statistics taken from the searched level. The level's own posterior, a
coarser grid resampled up, put the boundary inside the part: a pixel on the
outline mixes the part's colour with what lies beside it, a colour the part
does not show, and on the level that pixel is wider. LM-O's ape rendered at
its true poses over grey (every 4th render, learning seed 0), refined on the
level's posterior: fits a median 1.0 % too far (the image's edges alone:
0.6 % too near), AR_MSSD 0.77; on the full image's, 0.9 % and 0.81. On the
photos, every one, the same models: found in 2D 233 -> 240 of 745 targets,
AR_MSSD (the bench's thresholds, per target) 0.202 -> 0.207 (cat 0.364 ->
0.383, ape 0.285 -> 0.280); held-out objects 9-12, every 2nd photo, 123 ->
124 of 348, 0.218 -> 0.225 (duck 0.384 -> 0.411). Reading the full image's
bins costs about 1.6 ms at 640x480 and 9 ms for a 5 MP frame
(:func:`viewloc_core.colour_kernels.lookup_by_colour`).
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from viewloc_core.errors import InvalidInputError
from viewloc_core.feature_kernels import stronger_gradient
from viewloc_core.gradient import image_gradient
from viewloc_core.refine import EdgePyramid

#: Intensity per pixel that a unit step of P(part | colour) per pixel counts
#: as (intensities in [0, 1]): a step of the posterior from 0.9 to 0.1
#: within a pixel or two, a part of distinct colour, counts as an intensity
#: edge of 0.1-0.2 per pixel, a clear one (the refinement takes edges from
#: 0.02). Measured on the LM-O photos, AR_MSSD / AR_MSPD, every 4th photo,
#: learning seed 0: 0.1529 / 0.2106 without; 0.1598 / 0.2127 at 0.25;
#: 0.1741 / 0.2392 at 0.5; 0.1704 / 0.2429 at 1.0. At 0.5 on other models
#: and photos: seed 1 0.1698 / 0.2296 -> 0.1698 / 0.2413, seed 2 0.136 /
#: 0.1915 -> 0.1392 / 0.1974; every 2nd photo, seed 0 0.1371 / 0.1846 ->
#: 0.1423 / 0.1946, seed 1 0.1401 / 0.1889 -> 0.1431 / 0.1949; LM objects
#: the bench does not use (duck, eggbox, glue, hole puncher), every 2nd
#: photo: 0.1388 / 0.2144 -> 0.1678 / 0.2313. The cat gains on every seed;
#: the ape and the can move both ways: some fits at the part's place now
#: end 3-5 % too near rather than too far.
COLOUR_EDGE_WEIGHT = 0.5


def with_colour_boundary(
    edges: EdgePyramid, posterior: NDArray[np.floating], weight: float = COLOUR_EDGE_WEIGHT,
) -> EdgePyramid:
    """A gradient pyramid in which the part's colour boundary is an edge too.

    Parameters
    ----------
    edges : EdgePyramid
        The image's gradient pyramid (:func:`viewloc_core.refine.prepare_edges`);
        not modified.
    posterior : (h, w) float array
        P(part | colour) of each pixel, in [0, 1], on a grid of any size
        covering the same image (the full image's, so that the boundary
        lies where the image's own pixels put it): it is resampled to each
        level, pixel centres aligned.
    weight : float
        Intensity per pixel a unit posterior step per pixel counts as
        (positive).

    Returns
    -------
    EdgePyramid
        The same levels; at each pixel the image's gradient or ``weight``
        times the posterior's, whichever is stronger.
    """
    post = np.ascontiguousarray(posterior, dtype=np.float32)
    if post.ndim != 2 or min(post.shape) < 2:
        raise InvalidInputError(f"posterior must be a 2D map, got shape {post.shape}",
                                "posterior")
    if not weight > 0:
        raise InvalidInputError(f"weight must be positive, got {weight}", "weight")
    w = np.float32(weight)
    merged = []
    for grad in edges.gradients:
        height, width = grad.shape[:2]
        # Bilinear either way (cv2.resize keeps the pixel centres aligned):
        # the search level lies between the pyramid's first two levels.
        # Area averaging onto the smaller one was tried: AR_MSSD 0.163
        # against 0.174 (LM-O, every 4th photo).
        level_post = post if post.shape == (height, width) else np.asarray(
            cv2.resize(post, (width, height), interpolation=cv2.INTER_LINEAR), np.float32)
        gx, gy = image_gradient(level_post)
        # The image's gradient first: it stays on ties.
        merged.append(stronger_gradient(np.ascontiguousarray(grad, np.float32),
                                        np.ascontiguousarray(gx), np.ascontiguousarray(gy), w))
    return EdgePyramid(merged, edges.width, edges.height)
