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
then finer within it), each mask's outline that agrees with it carves it
once more to half a pixel, and its surface is extracted with marching cubes
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

import cv2
import numpy as np
import trimesh
from numba import njit
from numpy.typing import NDArray
from scipy import ndimage

from viewloc_core.both_cores import each_on_both, over_halves
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
#: part in one photo would otherwise cut that sliver off the hull for all
#: (the second pass, :data:`TRUSTED_MISS_SHARE`, lets the masks that agree
#: with the hull carve what this tolerance outvoted them on).
MISS_TOLERANCE_SHARE = 0.02

#: Largest share of the tolerant hull's voxels a mask's outline may cut off
#: (they lie more than half a pixel outside it) and still carve on its own
#: in :func:`visual_hull`'s second pass. The tolerance leaves a low bulge
#: where a sound mask is one of the few that see a region from outside:
#: such masks cut off up to 1.1 % (the hard bench set's bracket from 162
#: photos, a plate seen edge-on; boxes up to 0.9 %). A mask that lost half
#: the part cuts off half of it and stays outvoted.
TRUSTED_MISS_SHARE = 0.02

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

#: Fewer grid points than this are carved on one core: handing half of them
#: to the other costs more than it saves.
MIN_SPLIT_POINTS = 20_000

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


@njit(cache=True, nogil=True, inline="always")
def _projection_px(px: float, py: float, pz: float, R: NDArray[np.float64],
                   t: NDArray[np.float64], fx: float, fy: float, cx: float, cy: float,
                   ) -> tuple[float, float]:
    """Pixel (u, v) of the object point (px, py, pz) mm in the pinhole camera
    (R, t); (-2, -2), off every image, when it is behind the camera."""
    z = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2]
    if z <= 0.0:
        return -2.0, -2.0
    x = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]
    y = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
    return fx * x / z + cx, fy * y / z + cy


@njit(cache=True, nogil=True, inline="always")
def _bit(bits: NDArray[np.uint8], u: int, v: int) -> bool:
    """Pixel (u, v) of a mask packed along rows (big bit first); the caller
    keeps it in the image."""
    return (bits[v, u >> 3] >> (7 - (u & 7))) & 1 == 1


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
    height = mask_bits.shape[1]
    misses = np.zeros(len(points_mm), np.int32)
    # View by view over the points still kept (one mask stays in cache),
    # dropping those that missed too many.
    active = np.arange(len(points_mm))
    n_active = len(active)
    for k in range(mask_bits.shape[0]):
        R = rotations[k]
        t = translations_mm[k]
        bits = mask_bits[k]
        n_next = 0
        for a in range(n_active):
            i = active[a]
            u_px, v_px = _projection_px(points_mm[i, 0], points_mm[i, 1], points_mm[i, 2], R, t,
                                        fx, fy, cx, cy)
            u = int(math.floor(u_px + 0.5))
            v = int(math.floor(v_px + 0.5))
            if not (0 <= u < width and 0 <= v < height and _bit(bits, u, v)):
                misses[i] += 1
            if misses[i] <= tolerance:
                active[n_next] = i
                n_next += 1
        n_active = n_next
    return misses <= tolerance


@njit(cache=True, nogil=True)
def _outline_cuts(points_mm: NDArray[np.float64], rotations: NDArray[np.float64],
                  translations_mm: NDArray[np.float64], fx: float, fy: float, cx: float,
                  cy: float, outline_bits: NDArray[np.uint8], width: int,
                  max_cut: int) -> NDArray[np.bool_]:
    """Whether each point lies more than half a pixel outside a mask's
    outline that leaves out at most ``max_cut`` of the points.

    Half a pixel: the mask's bilinear interpolation is 0 at the point's
    projection (none of the four pixels around it is set); the outline lies
    half-way between a set pixel's centre and an unset one's.

    Parameters
    ----------
    points_mm, rotations, translations_mm, fx, fy, cx, cy, width
        As :func:`_kept`'s.
    outline_bits : (V, H, ceil(W / 8)) uint8
        The masks, their holes filled, packed as :func:`_kept`'s.
    max_cut : int

    Returns
    -------
    (N,) bool
    """
    height = outline_bits.shape[1]
    cut = np.zeros(len(points_mm), np.bool_)
    outside = np.empty(max_cut + 1, np.int64)
    for k in range(outline_bits.shape[0]):
        R = rotations[k]
        t = translations_mm[k]
        bits = outline_bits[k]
        n_outside = 0
        for i in range(len(points_mm)):
            u_px, v_px = _projection_px(points_mm[i, 0], points_mm[i, 1], points_mm[i, 2], R, t,
                                        fx, fy, cx, cy)
            u0 = int(math.floor(u_px))
            v0 = int(math.floor(v_px))
            if 0 <= u0 < width - 1 and 0 <= v0 < height - 1:
                # Both rows' two bits at once: their bytes ORed, shifted so
                # that u0's bit and the next are the lowest two.
                byte = u0 >> 3
                pair = (bits[v0, byte] | bits[v0 + 1, byte]) << 8
                if byte + 1 < bits.shape[1]:
                    pair |= bits[v0, byte + 1] | bits[v0 + 1, byte + 1]
                near = (pair >> (14 - (u0 & 7))) & 3 != 0
            else:
                near = False
                for v in range(max(v0, 0), min(v0 + 2, height)):
                    for u in range(max(u0, 0), min(u0 + 2, width)):
                        near = near or _bit(bits, u, v)
            if not near:
                outside[n_outside] = i
                n_outside += 1
                if n_outside > max_cut:
                    break
        if n_outside <= max_cut:
            for j in range(n_outside):
                cut[outside[j]] = True
    return cut


def _packed(mask: NDArray[np.bool_]) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """The mask, and the mask with its holes filled (every background region
    that does not reach the image's border), packed along rows.

    Parameters
    ----------
    mask : (H, W) bool

    Returns
    -------
    mask_bits, outline_bits : (H, ceil(W / 8)) uint8
    """
    # The background flooded from a frame one pixel wide around the image.
    framed = np.pad(mask.astype(np.uint8), 1)
    cv2.floodFill(framed, None, (0, 0), 2)
    return np.packbits(mask, axis=1), np.packbits(framed[1:-1, 1:-1] != 2, axis=1)


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
    # Packed to a bit a pixel: a thousand 1280x1024 masks are 160 MB, each
    # of the two stacks. Carved through the pinhole alone: the masks as the
    # camera without its lens distortion would see them.
    packed_shape = (len(views), camera.height, (camera.width + 7) // 8)
    mask_bits = np.empty(packed_shape, np.uint8)
    outline_bits = np.empty(packed_shape, np.uint8)
    for k, (m, _) in enumerate(views):
        mask_bits[k], outline_bits[k] = _packed(
            undistort(m.astype(np.uint8), camera, nearest=True)[0] > 0)
    rotations = np.stack([pose.R_m2c for _, pose in views]).astype(np.float64)
    translations = np.stack([pose.t_m2c for _, pose in views]).astype(np.float64)
    tolerance = int(MISS_TOLERANCE_SHARE * len(views))

    def carve(lo: NDArray[np.float64], hi: NDArray[np.float64], step: float,
              ) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
        points, shape = _grid(lo, hi, step)

        def kept_of(first: int, stop: int) -> tuple[NDArray[np.bool_]]:
            return (_kept(points[first:stop], rotations, translations, camera.fx, camera.fy,
                          camera.cx, camera.cy, mask_bits, camera.width, tolerance),)

        # The points are independent: half of them on each core.
        kept = np.asarray(over_halves(len(points), kept_of, MIN_SPLIT_POINTS)[0], np.bool_)
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
    # The masks whose outlines agree with this hull carve once more, each on
    # its own: the tolerance that outvotes a damaged mask also outvotes a
    # sound one where it is among the few that see a region from outside
    # (a box seen along an axis: the rim of its face toward the view is
    # carved by that view alone, and the hull's outline from there stood
    # out by 3 pixels). To half a pixel, not to the nearest pixel's centre:
    # that cut a box's edges back by over a pixel. Only outlines carve here
    # (holes filled): a hole a single mask has in its middle would bore a
    # tunnel through the hull.
    max_cut = int(TRUSTED_MISS_SHARE * len(kept))

    def cuts_of(masks: slice) -> NDArray[np.bool_]:
        return _outline_cuts(kept, rotations[masks], translations[masks], camera.fx, camera.fy,
                             camera.cx, camera.cy, outline_bits[masks], camera.width, max_cut)

    # Each mask cuts on its own: half of the masks on each core.
    middle = len(views) // 2
    inside = ~np.logical_or(*each_on_both(cuts_of, [slice(0, middle), slice(middle, None)]))
    occupied[occupied] = inside
    kept = kept[inside]
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
