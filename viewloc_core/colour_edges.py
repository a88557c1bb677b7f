"""The part's colour boundary as an edge the refinement fits to.

Where the scene's colours tell the part from what lies around it
(:mod:`viewloc_core.part_colour`), the probability that a pixel shows the
part, P(part | colour), steps from high to low across its outline. On real
photos that step is often clearer than the outline's intensity edge: the
part's own shading, texture and print put stronger edges just inside the
outline than the outline itself has against a background of like
brightness, and the refinement's search along the contour normals takes the
strongest edge it meets (LM-O photos: fits 3-7 % too far, their outline
shrunk onto edges inside the part).

:func:`with_colour_boundary` adds the posterior as one more channel of the
refinement's gradient pyramid, as the colour gradient already takes the
strongest of the image's channels at each pixel
(:func:`viewloc_core.gradient.image_gradient`): a pixel keeps the image's
gradient unless the weighted gradient of the posterior is stronger.
"""

from __future__ import annotations

import cv2
import numpy as np
from numba import njit
from numpy.typing import NDArray

from viewloc_core.errors import InvalidInputError
from viewloc_core.gradient import image_gradient
from viewloc_core.refine import EdgePyramid

F32 = NDArray[np.float32]

#: Intensity per pixel that a unit step of P(part | colour) per pixel counts
#: as (intensities in [0, 1]). The posterior's step across an outline spans
#: 0.5-0.8 over one to two pixels, so the boundary of a part of distinct
#: colour weighs about as much as an intensity edge of 0.1-0.2 per pixel, a
#: clear edge. Measured on LM-O photos, learning seed 0, AR_MSSD / AR_MSPD
#: (every 4th photo): 0.1529 / 0.2106 without; 0.1598 / 0.2127 at 0.25;
#: 0.1741 / 0.2392 at 0.5; 0.1704 / 0.2429 at 1.0.
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
        covering the same image (the colour cue's search level): it is
        resampled to each level, pixel centres aligned.
    weight : float
        Intensity per pixel a unit posterior step per pixel counts as
        (positive).

    Returns
    -------
    EdgePyramid
        The same levels; at each pixel the image's gradient or ``weight``
        times the posterior's, whichever is stronger.
    """
    post = np.asarray(posterior, dtype=np.float32)
    if post.ndim != 2 or min(post.shape) < 2:
        raise InvalidInputError(f"posterior must be a 2D map, got shape {post.shape}",
                                "posterior")
    if not weight > 0:
        raise InvalidInputError(f"weight must be positive, got {weight}", "weight")
    merged = []
    for grad in edges.gradients:
        height, width = grad.shape[:2]
        if post.shape != (height, width):
            # Bilinear either way (cv2.resize keeps the pixel centres
            # aligned): the search level lies between the pyramid's first
            # two levels, and area averaging on the smaller one, tried,
            # measured the same within the noise of LM-O (AR_MSSD 0.163
            # against 0.174, every 4th photo).
            level_post = cv2.resize(post, (width, height), interpolation=cv2.INTER_LINEAR)
        else:
            level_post = post
        gx, gy = image_gradient(np.ascontiguousarray(level_post, dtype=np.float32))
        out = grad.copy()
        _keep_stronger(out, gx, gy, np.float32(weight))
        merged.append(out)
    return EdgePyramid(merged, edges.width, edges.height)


@njit(cache=True, nogil=True)
def _keep_stronger(grad: F32, gx: F32, gy: F32, weight: np.float32) -> None:  # pragma: no cover
    """In place: each pixel of ``grad`` (H, W, 2) becomes ``weight * (gx, gy)``
    where that is the stronger gradient."""
    for y in range(grad.shape[0]):
        for x in range(grad.shape[1]):
            px = weight * gx[y, x]
            py = weight * gy[y, x]
            if px * px + py * py > grad[y, x, 0] * grad[y, x, 0] + grad[y, x, 1] * grad[y, x, 1]:
                grad[y, x, 0] = px
                grad[y, x, 1] = py


def warm_up() -> None:
    """Compile (or load from numba's cache) :func:`_keep_stronger`."""
    grad = np.zeros((2, 2, 2), np.float32)
    _keep_stronger(grad, np.ones((2, 2), np.float32), np.zeros((2, 2), np.float32),
                   np.float32(1.0))
