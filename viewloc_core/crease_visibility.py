"""Whether a part's sharp creases show as edges in its own training views.

The refinement (:mod:`viewloc_core.refine`) fits the outline and the sharp
creases of the part to the image edges, and scores a fit by the share of them
that find an edge. The outline is an edge against almost any background; a
crease is one only where its two faces differ in brightness. On a dark part
(black plastic, anodised metal) they hardly ever do: the crease points then
find the outline a few pixels away and pull the fit off, and no fit can
confirm more than the outline's share, so a right fit scores like a wrong one.
Whether that is so is a property of the part, not of one fit (at a wrong
place in clutter the creases find nothing either), so it is decided once,
at learning, from the training views rendered under varied lights: the
creases are kept when they find their edges about as often as the outline.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from viewloc_core.camera import Camera
from viewloc_core.contour_model import KIND_CREASE, OUTLINE_KINDS, ContourModel
from viewloc_core.pose import Pose
from viewloc_core.refine import (
    RefineOptions,
    edges_along_normals,
    prepare_edges,
    project_contour_view,
)

#: The creases are kept when the share of their points that find an edge in
#: the training views is at least this share of the outline's. Measured
#: (creases / outline): an L-bracket of grey level 25 0.17 / 0.84, of 60
#: 0.41 / 0.85, of 128 0.58 / 0.86, untextured 0.61 / 0.86; bench parts:
#: barbell 0.79 / 0.92, bracket 0.75 / 0.90, LM-O ape 0.48 / 0.95, can
#: 0.50 / 0.95, cat 0.52 / 0.95, driller 0.64 / 0.95 (scanned meshes have
#: few creases, about 1 % of their contour points); free-form has none.
MIN_CREASE_SHARE = 0.5

#: Half-length (pixels) of the search along each normal in a training view:
#: the points are projected with the pose the view was rendered at, so only
#: the contour model's own sampling error separates them from their edges.
_SEARCH_PX = 2


def confirmed_shares(
    contour: ContourModel,
    images: Sequence[NDArray[np.generic]],
    rotations: Sequence[NDArray[np.float64]],
    camera: Camera,
    d0_mm: float,
) -> tuple[float, float]:
    """Shares of the outline's and of the creases' points that find an edge
    in the views they were rendered in.

    Parameters
    ----------
    contour : ContourModel
        The part's contour points, in the frame the views were rendered in.
    images : sequence of (H, W, 3) uint8
        Training views (what the features were taken from).
    rotations : sequence of (3, 3) float64
        Part -> camera rotation of each view; the part's origin is ``d0_mm``
        in front of the camera.
    camera : Camera
        The training camera.
    d0_mm : float
        Distance of the part's origin, mm.

    Returns
    -------
    outline, creases : float
        Shares in [0, 1]; ``nan`` for a kind with no point seen.
    """
    options = RefineOptions()
    cos_max = math.cos(math.radians(options.max_angle_deg))
    found: dict[int | tuple[int, ...], list[int]] = {OUTLINE_KINDS: [0, 0], KIND_CREASE: [0, 0]}
    for image, R in zip(images, rotations, strict=True):
        pose = Pose(np.asarray(R, np.float64), np.array([0.0, 0.0, d0_mm]))
        grad = prepare_edges(image, 1).gradients[0]
        for kind, tally in found.items():
            projected = project_contour_view(camera, contour, pose, kind)
            if projected is None:
                continue
            uv, n2 = projected
            ok, offset = edges_along_normals(grad, uv, n2, _SEARCH_PX, options.min_gradient,
                                             cos_max)
            tally[0] += int(np.count_nonzero(ok & (np.abs(offset) <= options.inlier_px)))
            tally[1] += len(uv)

    def share(kind: int | tuple[int, ...]) -> float:
        hits, total = found[kind]
        return hits / total if total else math.nan

    return share(OUTLINE_KINDS), share(KIND_CREASE)


def creases_show(outline_share: float, crease_share: float) -> bool:
    """Whether the creases find their edges about as often as the outline
    (see MIN_CREASE_SHARE); True when either share is unknown."""
    if math.isnan(outline_share) or math.isnan(crease_share):
        return True
    return crease_share >= MIN_CREASE_SHARE * outline_share
