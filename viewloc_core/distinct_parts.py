"""Distinct parts: which detections claim the same pixels, and so the same part.

Two rigid parts cannot fill the same stretch of the image both in front:
where two fits cover mostly the same pixels, one of them is a second,
worse fit of the same part (a neighbouring location that the refinement
pulled onto it, a rival view, a colour proposal beside an aligned one).
With more than one detection wanted, such a fit takes a place in the
answer that belongs to another part (bench parts, 3-5 copies on a plain
background, 10 scenes each: of the fits that missed a copy, 7 of 12
L-brackets' and 4 of 6 clamps' lay on a copy already found).

A fit's footprint is the set of cells of a coarse grid its visible surface
samples fall in (:func:`viewloc_core.shading.visible_samples`). Two fits
are the same part when the cells they share are at least
:data:`SAME_PART_OVERLAP` of the smaller footprint: two parts lying side by
side touch along a line of cells at most, one resting on another hides
what it covers. Without a mesh the footprint is unknown and the projected
centres decide: closer than :data:`SAME_PART_CENTRE_SHARE` of the part's
image diameter.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from viewloc_core.camera import Camera
from viewloc_core.pose import Pose
from viewloc_core.shading import SurfaceSamples, visible_samples

#: Share of the smaller footprint two fits of one part have in common, at
#: least (a fit of the same part a few pixels or degrees off shares most
#: of it; two parts side by side share the cells along their contact).
SAME_PART_OVERLAP = 0.5

#: Grid cells across the part's image diameter: fine enough that parts
#: side by side share few cells, coarse enough that the surface samples
#: leave no holes (no finer than their own spacing in the image).
CELLS_PER_DIAMETER = 24

#: Without a mesh: projected centres closer than this share of the part's
#: image diameter are one part.
SAME_PART_CENTRE_SHARE = 0.5


def footprint(samples: SurfaceSamples, camera: Camera, pose: Pose,
              cell_px: float) -> NDArray[np.int64]:
    """Grid cells the part's visible surface falls in at ``pose``.

    Parameters
    ----------
    samples : SurfaceSamples
        The part's surface, in the frame ``pose`` maps from (mm).
    camera : Camera
    pose : Pose
        Part frame -> camera.
    cell_px : float
        Side of a grid cell, pixels (> 0).

    Returns
    -------
    (K,) int64
        Sorted unique cell ids (row-major over a grid covering the image and
        a margin of one image around it); empty when no sample is seen.
    """
    uv = visible_samples(samples, camera, pose).uv
    if not len(uv):
        return np.zeros(0, np.int64)
    cols = int(np.ceil(camera.width / cell_px)) + 2
    ij = np.floor(uv / cell_px).astype(np.int64) + 1
    return np.unique(ij[:, 1] * cols + ij[:, 0])


def _cell_px(samples: SurfaceSamples, camera: Camera, pose: Pose, diameter_mm: float) -> float:
    """Grid cell side for a part at ``pose``: CELLS_PER_DIAMETER across its
    image diameter, but at least twice the spacing of its surface samples
    in the image (no holes between them)."""
    z = max(float(pose.t_m2c[2]), 1e-6)
    per_mm = camera.fx / z
    return max(per_mm * diameter_mm / CELLS_PER_DIAMETER, 2.0 * per_mm * samples.spacing_mm, 1.0)


def distinct_parts(
    poses: Sequence[Pose], camera: Camera, diameter_mm: float,
    samples: SurfaceSamples | None = None, limit: int | None = None,
) -> list[int]:
    """Indices of the poses that are each a part of its own, best first.

    Parameters
    ----------
    poses : sequence of Pose
        Fits best first, part frame (the frame of ``samples``) -> camera.
    camera : Camera
    diameter_mm : float
        The part's diameter.
    samples : SurfaceSamples or None
        The part's surface; None compares projected centres instead.
    limit : int or None
        Stop once this many are kept (the rest are not looked at).

    Returns
    -------
    list of int
        Increasing indices: each pose that is not the same part as an
        earlier kept one.
    """
    if samples is None:
        return _distinct_by_centre(poses, camera, diameter_mm, limit)
    return _distinct_by_footprint(poses, camera, diameter_mm, samples, limit)


def _distinct_by_footprint(poses: Sequence[Pose], camera: Camera, diameter_mm: float,
                           samples: SurfaceSamples, limit: int | None) -> list[int]:
    """:func:`distinct_parts` with the part's surface: footprints decide."""
    if not poses:
        return []
    # One grid for every fit of the image, sized by the best fit (fits of
    # one part are within a few % of each other's depth).
    cell_px = _cell_px(samples, camera, poses[0], diameter_mm)
    kept: list[int] = []
    cells: list[NDArray[np.int64]] = []
    for i, pose in enumerate(poses):
        if limit is not None and len(kept) >= limit:
            break
        mine = footprint(samples, camera, pose, cell_px)
        same = len(mine) > 0 and any(
            len(other) > 0 and np.intersect1d(mine, other, assume_unique=True).size
            >= SAME_PART_OVERLAP * min(len(mine), len(other))
            for other in cells)
        if not same:
            kept.append(i)
            cells.append(mine)
    return kept


def _distinct_by_centre(poses: Sequence[Pose], camera: Camera, diameter_mm: float,
                        limit: int | None) -> list[int]:
    """:func:`distinct_parts` without a mesh: projected centres decide."""
    kept: list[int] = []
    centres: list[tuple[NDArray[np.float64], float]] = []
    for i, pose in enumerate(poses):
        if limit is not None and len(kept) >= limit:
            break
        centre = camera.project(pose.t_m2c[None])[0]
        diameter_px = camera.fx * diameter_mm / max(float(pose.t_m2c[2]), 1e-6)
        if not any(np.hypot(*(centre - c)) < SAME_PART_CENTRE_SHARE * min(d, diameter_px)
                   for c, d in centres):
            kept.append(i)
            centres.append((centre, diameter_px))
    return kept
