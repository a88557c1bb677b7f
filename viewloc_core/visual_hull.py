"""The visual hull of a part from masked training photos (shape from silhouette).

A part learned from photos has no mesh, so its fits cannot be refined on the
image's edges (paper §5.2): its pose is its nearest training view's, turned
in the image plane, tens of degrees coarse. Photos with masks and known
viewpoints say more than that: the part lies, in every photo, inside its
mask's cone, and the intersection of those cones (the visual hull,
Laurentini 1994) is a mesh whose outline from each training direction is the
photo's own. The hull's outline is learned as the part's contour model
(:func:`viewloc_core.learn.learn_from_images`), without its creases: those
are where the cones meet, not the part's edges.

The hull is carved on a voxel grid (coarse first, to find the part's box,
then finer within it) and its surface extracted with marching cubes
(:func:`skimage.measure.marching_cubes`). It is larger than the part where
no photo sees a concavity from the side: a cup's inside, the space between
a fork's tines.

The hull is carved in the photos' own pixels, not in the canonical training
views they are warped into: those have about 128 pixels across the part, and
the hull would be as coarse. The object frame is the photos': its origin is
the point they put on their optical axes, in mm.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import trimesh
from numba import njit
from numpy.typing import NDArray
from scipy import ndimage

from viewloc_core.camera import Camera, undistort
from viewloc_core.mesh_simplify import simplified
from viewloc_core.pose import Pose
from viewloc_core.view_sphere import spiral_directions

#: Voxels along the hull box's longest side on the fine grid: the outline
#: then steps at under 1 % of the part's size, finer than the training
#: views' pixels (about 1/150 of the diameter at the default object_px).
HULL_VOXELS = 160

#: Voxels along each side of the coarse grid that finds the part's box.
COARSE_VOXELS = 40

#: Share of the masked views whose mask a voxel may fall outside and still
#: be kept: a hand-drawn or thresholded mask that misses a sliver of the
#: part in one photo would otherwise cut that sliver off the hull for all.
MISS_TOLERANCE_SHARE = 0.02

#: Fewest masked views a hull is carved from, and the largest angle between
#: any viewing direction and the nearest photo's (:func:`unseen_angle_deg`).
#: Where no photo grazes a flat face, the hull bulges over it, by up to the
#: face's half-width times the tangent of half the views' spacing; where no
#: photo looks from at all (a part photographed on a table, from above
#: only: 99°), the hull is a column through the table, no shape of the
#: part's. The hard bench set's two parts learned from N photos spread
#: evenly over the sphere (hard-photos; AR_MSSD / AR_MSPD): N = 20 (unseen
#: angle 34.5°) 0.68 / 0.74, 30 (28°) 0.70 / 0.75, 42 0.76 / 0.84, 60 0.80 /
#: 0.88, 80 0.81 / 0.88, 162 0.78 / 0.84; from 42 without a hull 0.23 /
#: 0.33 (the rotation is then the nearest view's). The tests' bracket, three
#: plain scenes: from 16-30 spread photos, fitted within 1.5° in 2-3 of
#: them (24: one), without a hull 180° off or not found; from the view
#: sphere's 12 directions (37°) at wrong places in two.
MIN_HULL_VIEWS = 20
MAX_UNSEEN_ANGLE_DEG = 36.0

#: Directions :func:`unseen_angle_deg` probes.
UNSEEN_PROBES = 10_000

#: Half the side of the cube searched for the part, as a share of its
#: diameter: the canonical views show 1.25 diameters about the origin, and
#: the part must lie in them.
SEARCH_HALF_SIDE_SHARE = 0.75

#: Faces the hull is simplified to (:mod:`viewloc_core.mesh_simplify`):
#: marching cubes on the fine grid gives about 100,000. At 15,000 the
#: contour model's 642 views (``LearningConfig.contour_level``) render the
#: hull itself within ``learn.CONTOUR_FACE_RENDERS``. At 20,000 they used
#: to fall back to 162 directions (16° apart), whose outlines project inside
#: the true one where the surface is curved. Hard bench set, learned from 162
#: photos, 20,000 (162 contour views) -> 15,000 faces, learning seeds 0 / 1:
#: 6D recognition 0.68 / 0.7375 -> 0.72 / 0.775, AR_MSSD 0.787 / 0.831 ->
#: 0.799 / 0.846, AR_MSPD 0.849 / 0.901 -> 0.849 / 0.895; the free-form
#: part's depth error median 5.1 / 5.1 -> 2.7 / 2.8 mm (the bracket's 7.8 /
#: 7.8 -> 7.0 / 8.0); learning 7 -> 10-11 s.
HULL_MAX_FACES = 15_000

#: Smoothing (voxels) of the carved occupancy before the surface is
#: extracted: marching cubes on a 0/1 grid leaves a staircase of 45° facets
#: that would read as creases.
SMOOTHING_VOXELS = 0.8

#: Taubin smoothing of the surface (Taubin 1995: per iteration a shrinking
#: step of ``TAUBIN_LAMBDA`` and an inflating one of ``TAUBIN_MU``, so the
#: volume stays). Marching cubes leaves facets several degrees off the true
#: surface however smooth the field, and the shading cue reads the hull's
#: normals to tell a part's sides apart. The hard set's free-form part from
#: 162 photos: normals a median 6.2° off the mesh's without it, 2.8° after 5
#: iterations, 2.1° after 10, 1.7° after 20 (the surface 0.26, 0.27, 0.28,
#: 0.31 mm from the mesh); its AR_MSSD / AR_MSPD 0.605 / 0.673 -> 0.76 /
#: 0.805 with 10.
TAUBIN_LAMBDA = 0.5
TAUBIN_MU = -0.53
TAUBIN_ITERATIONS = 10


@njit(cache=True, nogil=True)
def _kept(points_mm: NDArray[np.float64], rotations: NDArray[np.float64],
          translations_mm: NDArray[np.float64], fx: float, fy: float, cx: float, cy: float,
          mask_bits: NDArray[np.uint8], width: int, tolerance: int) -> NDArray[np.bool_]:
    """Whether each point projects into the background (or out of the
    image) of at most ``tolerance`` of the masks.

    Parameters
    ----------
    points_mm : (N, 3) float64
        Points in the object frame, mm.
    rotations, translations_mm : (V, 3, 3), (V, 3) float64
        Per photo, object to camera.
    fx, fy, cx, cy : float
        The photos' pinhole camera, pixels.
    mask_bits : (V, H, ceil(W / 8)) uint8
        The masks, packed along rows (:func:`numpy.packbits`, big bit first).
    width : int
        W, pixels.
    tolerance : int

    Returns
    -------
    (N,) bool
    """
    n_views, height = mask_bits.shape[0], mask_bits.shape[1]
    misses = np.zeros(len(points_mm), np.int32)
    # View by view over the points still kept (one mask stays in cache),
    # dropping those that missed too many.
    active = np.arange(len(points_mm))
    n_active = len(active)
    for k in range(n_views):
        R = rotations[k]
        t = translations_mm[k]
        n_next = 0
        for a in range(n_active):
            i = active[a]
            px, py, pz = points_mm[i, 0], points_mm[i, 1], points_mm[i, 2]
            z = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2]
            hit = False
            if z > 0.0:
                x = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]
                y = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
                u = int(math.floor(fx * x / z + cx + 0.5))
                v = int(math.floor(fy * y / z + cy + 0.5))
                if 0 <= u < width and 0 <= v < height:
                    hit = (mask_bits[k, v, u >> 3] >> (7 - (u & 7))) & 1 == 1
            if not hit:
                misses[i] += 1
            if misses[i] <= tolerance:
                active[n_next] = i
                n_next += 1
        n_active = n_next
    return misses <= tolerance


def _grid(lo: NDArray[np.float64], hi: NDArray[np.float64], step: float,
          ) -> tuple[NDArray[np.float64], tuple[int, int, int]]:
    """Voxel centres (N, 3) of the box ``lo``..``hi`` at ``step`` mm, x
    slowest, and the grid's shape."""
    axes = [lo[k] + step * (np.arange(int(np.ceil((hi[k] - lo[k]) / step)) + 1))
            for k in range(3)]
    shape = (len(axes[0]), len(axes[1]), len(axes[2]))
    xx, yy, zz = np.meshgrid(*axes, indexing="ij")
    return np.column_stack([xx.ravel(), yy.ravel(), zz.ravel()]), shape


def unseen_angle_deg(poses: Sequence[Pose]) -> float:
    """The largest angle between a viewing direction and the nearest photo's.

    Parameters
    ----------
    poses : sequence of Pose
        Per photo, object to camera (mm).

    Returns
    -------
    float
        Degrees, measured on :data:`UNSEEN_PROBES` directions spread evenly
        (about 2° apart); 180 without photos.
    """
    if not poses:
        return 180.0
    # Each photo's camera centre in the object frame.
    centres = np.stack([pose.inverse().t_m2c for pose in poses])
    seen = centres / np.linalg.norm(centres, axis=1, keepdims=True)
    probe = spiral_directions(UNSEEN_PROBES)
    nearest_cos = np.clip((probe @ seen.T).max(axis=1), -1.0, 1.0)
    return float(np.degrees(np.arccos(nearest_cos.min())))


def visual_hull(masks: Sequence[NDArray[np.generic] | None], poses: Sequence[Pose],
                camera: Camera, diameter_mm: float,
                voxels: int = HULL_VOXELS) -> trimesh.Trimesh | None:
    """The part's visual hull from its masked photos, or None when too few
    photos have masks, they leave a side of the part unseen (see
    :data:`MAX_UNSEEN_ANGLE_DEG`) or the masks agree on no volume.

    Parameters
    ----------
    masks : sequence of (H, W) arrays or None
        Per photo, non-zero on the part (None: no mask).
    poses : sequence of Pose
        Per photo, object to camera (mm).
    camera : Camera
        The photos' camera.
    diameter_mm : float
        The part's diameter; it lies within SEARCH_HALF_SIDE_SHARE of it
        from the object origin.
    voxels : int
        Voxels along the longest side of the part's box.

    Returns
    -------
    trimesh.Trimesh or None
        Watertight mesh in the object frame, mm, its largest connected piece.
    """
    views = [(np.asarray(m) > 0, pose) for m, pose in zip(masks, poses, strict=True)
             if m is not None]
    if (len(views) < MIN_HULL_VIEWS
            or unseen_angle_deg([pose for _, pose in views]) > MAX_UNSEEN_ANGLE_DEG):
        return None
    # Packed to a bit a pixel: a thousand 1280x1024 masks are 160 MB.
    # Carved through the pinhole alone: the masks as the camera without its
    # lens distortion would see them.
    mask_bits = np.stack([np.packbits(undistort(m.astype(np.uint8), camera, nearest=True)[0] > 0,
                                      axis=1) for m, _ in views])
    rotations = np.stack([pose.R_m2c for _, pose in views]).astype(np.float64)
    translations = np.stack([pose.t_m2c for _, pose in views]).astype(np.float64)
    tolerance = int(MISS_TOLERANCE_SHARE * len(views))

    def carve(lo: NDArray[np.float64], hi: NDArray[np.float64], step: float,
              ) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
        points, shape = _grid(lo, hi, step)
        kept = _kept(points, rotations, translations, camera.fx, camera.fy, camera.cx,
                     camera.cy, mask_bits, camera.width, tolerance)
        return kept.reshape(shape), points[kept]

    half = SEARCH_HALF_SIDE_SHARE * diameter_mm
    coarse_step = 2.0 * half / (COARSE_VOXELS - 1)
    _, coarse_kept = carve(np.full(3, -half), np.full(3, half), coarse_step)
    if len(coarse_kept) == 0:
        return None
    # The box of the coarse survivors, one coarse voxel wider on each side:
    # a fine voxel can survive where its coarse neighbour's centre did not.
    lo = coarse_kept.min(axis=0) - coarse_step
    hi = coarse_kept.max(axis=0) + coarse_step
    step = float((hi - lo).max()) / voxels
    occupied, kept = carve(lo, hi, step)
    if len(kept) < 8:
        return None
    from skimage.measure import marching_cubes

    # Padded with empty voxels so the surface closes at the box's faces.
    field = ndimage.gaussian_filter(np.pad(occupied.astype(np.float32), 2), SMOOTHING_VOXELS)
    vertices, faces, _, _ = marching_cubes(field, level=0.5, spacing=(step, step, step))
    vertices = vertices + (lo - 2.0 * step)
    hull = trimesh.Trimesh(vertices, faces, process=True)
    pieces = hull.split(only_watertight=False)
    if len(pieces) > 1:
        hull = max(pieces, key=lambda piece: len(piece.faces))
    if hull.volume < 0:
        hull.invert()
    trimesh.smoothing.filter_taubin(hull, lamb=TAUBIN_LAMBDA, nu=TAUBIN_MU,
                                    iterations=TAUBIN_ITERATIONS)
    return simplified(hull, HULL_MAX_FACES)
