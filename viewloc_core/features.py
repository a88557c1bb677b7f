"""Edge-based features of one image (Pope & Lowe's hierarchy, DESIGN.md §2 step 3).

From a grey or colour image (8 or 16 bit) this extracts

- **edge samples**: oriented edge pixels ``(x, y, θ)``, dense, used to verify
  and refit alignments and by the pose refinement;
- **segments**: straight edge segments (LSD, Grompone von Gioi et al. 2010);
- **junctions**: pairs of segments meeting at a vertex (L-junctions/corners);
- **U-junctions**: a segment with a junction at each end, both arms on the
  same side (:mod:`viewloc_core.u_junctions`);
- **parallel pairs**: two overlapping, nearly parallel segments;
- **arcs**: circular arcs fitted to chains of edge pixels (discs and holes
  seen end-on give few straight segments but clean circles).

Every grouped feature has a position ``b = (x, y, θ, s)`` (pixels, radians,
pixels) and similarity-invariant attributes ``a``. No feature depends on
absolute brightness or on the sign of the contrast: orientations are taken
modulo π, detection thresholds are relative to the image's own gradient
statistics, so a light part on a dark table and a dark part on a light table
give the same features.
"""

from __future__ import annotations

import threading
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from viewloc_core.errors import InvalidImageError
from viewloc_core.feature_kernels import (
    CLOSED_CIRCLE,
    NO_ARC,
    arc_runs,
    chain_pieces,
    fit_circles,
    parallel_pair_parts,
    piece_chunks,
    pixels_near_circles,
    prune_circles,
    refit_on_pixels,
    scaled_int16,
    spread_bits,
    window_bin_counts,
)
from viewloc_core.gradient import image_gradient
from viewloc_core.near_pairs import pairs_within
from viewloc_core.u_junctions import u_junctions

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]

#: Orientation bins over [0, π) for the spread orientation maps (LINE-2D style).
ORIENTATION_BINS = 16

#: Feature kinds; a model feature only pairs with an image feature of its kind.
KIND_JUNCTION = 0
KIND_PARALLEL = 1
KIND_ARC = 2
KIND_U_JUNCTION = 3


@dataclass(frozen=True, slots=True)
class FeatureConfig:
    """Tuning of the feature extractor.

    Attributes
    ----------
    min_segment_px : float
        Shorter LSD segments are discarded.
    junction_gap_frac : float
        Two segment ends join when closer than this fraction of the shorter
        segment (plus ``junction_gap_px``).
    junction_gap_px : float
        Absolute slack for the junction gap, pixels.
    min_junction_angle_deg : float
        Junctions flatter than this (or sharper than 180 minus it) are dropped:
        their bisector is ill-defined.
    parallel_max_angle_deg : float
        Largest angle between the two segments of a parallel pair.
    edge_low_frac, edge_high_frac : float
        Canny hysteresis thresholds as fractions of the 98th percentile of the
        gradient magnitude, so the edge map does not depend on exposure.
    strong_edge_frac : float
        An edge pixel is strong when its gradient is at least this fraction
        of the same 98th percentile (in a nearly empty image, of the floor's
        equivalent). Faint texture (a sprayed or noisy surface) lies below it,
        a part's outline against it above; :mod:`viewloc_core.edge_evidence`
        weighs hits on strong edges apart, and the texture test spares them.
    edge_floor_lsb : float
        Neither threshold goes below this gradient, in quantisation steps
        (LSB of the image's integer type) per pixel. In a nearly empty, smooth
        image the 98th percentile is the ramp between two grey levels, and
        without a floor the banding of a smooth gradient becomes edges. One
        LSB per pixel is a step of about 2.5 grey levels after the smoothing.
    arc_min_radius_px, arc_max_radius_px : float
        Radius range of circular arcs, pixels.
    arc_min_span_deg : float
        Arcs covering less of their circle are dropped (their centre and
        radius are poorly determined and a gently bent line would pass).
        ``align._log_background_density`` assumes this value (80).
    arc_max_rms_px, arc_max_rms_frac : float
        Largest RMS distance of an arc's pixels from its circle: the larger
        of the absolute value and the fraction of the radius (slightly
        oblique circles are ellipses that a circle fits within a few percent).
    texture_radius_px : int
        Half-size of the window in which an edge pixel's surround is examined
        for texture.
    texture_other_density : float
        An edge pixel is texture, and dropped, when more than this share of
        the pixels in its window are edges of other orientations (more than
        ±22.5° off its own) and it is not strong (``strong_edge_frac``); 1
        or more switches the suppression off.
    """

    min_segment_px: float = 7.0
    junction_gap_frac: float = 0.25
    junction_gap_px: float = 3.0
    min_junction_angle_deg: float = 25.0
    parallel_max_angle_deg: float = 8.0
    edge_low_frac: float = 0.08
    edge_high_frac: float = 0.2
    strong_edge_frac: float = 1.0
    edge_floor_lsb: float = 1.0
    arc_min_radius_px: float = 10.0
    arc_max_radius_px: float = 400.0
    arc_min_span_deg: float = 80.0
    arc_max_rms_px: float = 0.6
    arc_max_rms_frac: float = 0.006
    texture_radius_px: int = 12
    texture_other_density: float = 0.15


@dataclass(frozen=True, slots=True)
class GroupedFeatures:
    """Sparse features with position and attributes (one row per feature).

    Attributes
    ----------
    kind : (F,) int8
        KIND_JUNCTION, KIND_PARALLEL, KIND_ARC or KIND_U_JUNCTION.
    xy : (F, 2) float32
        Position, pixels (arc: centre of its circle).
    theta : (F,) float32
        Orientation, radians in [0, 2π) (junction bisector; arc: direction
        from the centre to the middle of the arc; U-junction: the base's
        normal towards the arms) or [0, π) (parallel).
    scale : (F,) float32
        Size, pixels (junction: geometric mean of arm lengths; parallel pair:
        separation of the two lines; arc: radius; U-junction: base length).
    attrs : (F, 2) float32
        Similarity-invariant attributes. Junction: (opening angle in radians,
        log arm-length ratio). Parallel pair: (log overlap/separation,
        log length ratio). Arc: (angular span in radians, 0). U-junction:
        (mean, half difference of its two opening angles, radians).
    """

    kind: NDArray[np.int8]
    xy: F32
    theta: F32
    scale: F32
    attrs: F32

    def __len__(self) -> int:
        return int(self.kind.shape[0])

    def select(self, index: NDArray[np.bool_] | NDArray[np.int64]) -> GroupedFeatures:
        """Subset by boolean mask or index array."""
        return GroupedFeatures(
            self.kind[index], self.xy[index], self.theta[index], self.scale[index],
            self.attrs[index],
        )


@dataclass(frozen=True, slots=True)
class ImageFeatures:
    """Everything extracted from one image.

    Attributes
    ----------
    edge_xy : (E, 2) float32
        Edge pixel positions.
    edge_theta : (E,) float32
        Edge (tangent) orientation modulo π, radians.
    segments : (S, 4) float32
        Segment end points ``x1, y1, x2, y2``.
    grouped : GroupedFeatures
        Junctions, U-junctions, parallel pairs and arcs.
    orientation_bits : (H, W) uint16
        Bit ``b`` set where an edge of orientation bin ``b`` lies within the
        spread radius (LINE-2D's spread map); for fast verification.
    strong_bits : (H, W) uint16
        The same map of the strong edge pixels alone
        (``FeatureConfig.strong_edge_frac``): a subset of ``orientation_bits``.
    nearest_edge : (H, W) int32
        Index into ``edge_xy`` of the edge pixel nearest to each pixel (-1
        when the image has no edges).
    edge_distance : (H, W) float32
        Distance to that edge pixel, pixels.
    shape : tuple of int
        Image (height, width).
    """

    edge_xy: F32
    edge_theta: F32
    segments: F32
    grouped: GroupedFeatures
    orientation_bits: NDArray[np.uint16]
    strong_bits: NDArray[np.uint16]
    nearest_edge: NDArray[np.int32]
    edge_distance: F32
    shape: tuple[int, int]

    def nearest_edges(
        self, uv: NDArray[np.floating], max_distance: float
    ) -> tuple[NDArray[np.bool_], NDArray[np.int64]]:
        """Nearest edge pixel of each query point, by table look-up.

        Parameters
        ----------
        uv : (N, 2) array
            Query points, pixels.
        max_distance : float
            Larger distances count as no match.

        Returns
        -------
        found : (N,) bool
        index : (N,) int64
            Index into ``edge_xy`` (meaningful where ``found``).
        """
        h, w = self.shape
        u = np.rint(uv[:, 0]).astype(np.int64)
        v = np.rint(uv[:, 1]).astype(np.int64)
        inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        index = np.zeros(len(uv), np.int64)
        found = np.zeros(len(uv), bool)
        if len(self.edge_xy) == 0:
            return found, index
        index[inside] = self.nearest_edge[v[inside], u[inside]]
        found[inside] = self.edge_distance[v[inside], u[inside]] <= max_distance
        return found, index


#: The shortest image side the features work on, pixels.
MIN_IMAGE_SIDE_PX = 16


def to_grey_float(image: NDArray[np.generic]) -> F32:
    """Grey image as float32 in [0, 1] from (H, W) or (H, W, 3|4), uint8 or uint16.

    Colour is reduced by the per-pixel maximum over channels rather than
    luminance: an edge between two colours of equal luminance stays visible.
    """
    arr = np.asarray(image)
    if arr.ndim == 3 and arr.shape[2] in (3, 4):
        arr = arr[:, :, :3]
    elif arr.ndim != 2:
        raise InvalidImageError(f"image must be (H, W) or (H, W, 3), got {arr.shape}", "image")
    if arr.shape[0] < MIN_IMAGE_SIDE_PX or arr.shape[1] < MIN_IMAGE_SIDE_PX:
        raise InvalidImageError(
            f"image too small: {arr.shape[1]}x{arr.shape[0]} pixels where the search reads "
            f"it, at least {MIN_IMAGE_SIDE_PX} on each side", "image")
    if arr.ndim == 3 and arr.dtype in (np.uint8, np.uint16):
        # Channel maximum before the float conversion: three times less work.
        arr = np.maximum(np.maximum(arr[:, :, 0], arr[:, :, 1]), arr[:, :, 2])
    if arr.dtype == np.uint8:
        grey = arr.astype(np.float32) / 255.0
    elif arr.dtype == np.uint16:
        grey = arr.astype(np.float32) / 65535.0
    elif np.issubdtype(arr.dtype, np.floating):
        grey = np.nan_to_num(arr.astype(np.float32))
    else:
        raise InvalidImageError(f"unsupported image dtype {arr.dtype}", "image")
    if grey.ndim == 3:
        grey = grey.max(axis=2)
    return np.ascontiguousarray(grey)


def extract_features(
    image: NDArray[np.generic],
    config: FeatureConfig = FeatureConfig(),
    mask: NDArray[np.bool_] | None = None,
    spread_px: int = 2,
    edges_only: bool = False,
) -> ImageFeatures:
    """Extract edge samples, segments, junctions and parallel pairs.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array, uint8 / uint16 / float
        The image.
    config : FeatureConfig
        Tuning.
    mask : (H, W) bool, optional
        Keep only features on (a slightly dilated) mask, for training views.
    spread_px : int
        Radius of the orientation spreading for verification, pixels.
    edges_only : bool
        Only the edge pixels and their maps: no segments, junctions,
        parallel pairs or arcs (what the view search reads, at about a
        third of the cost: no line detection).

    Returns
    -------
    ImageFeatures
    """
    grey = to_grey_float(image)
    h, w = grey.shape
    smooth = np.asarray(cv2.GaussianBlur(grey, (0, 0), 1.0), np.float32)
    # LSD needs nothing of what follows (its segments are masked afterwards)
    # and OpenCV releases the GIL, as do numpy's partition and its loops over
    # large arrays: it runs on the other core meanwhile, from as early as it
    # can, so that the other core is free again for the distance transform
    # below.
    lines = None if edges_only else _POOL.submit(_detect_lines, smooth)
    gx, gy = _gradient(image, smooth)
    mag = cv2.magnitude(gx, gy)
    # A strided sample is plenty for a percentile and four times cheaper.
    ref = float(np.percentile(mag[::2, ::2], 98.0))
    g_max = float(max(np.abs(gx).max(), np.abs(gy).max()))
    if g_max <= 1e-6:
        return _empty_features((h, w))
    floor_gradient = config.edge_floor_lsb * _quantisation_step(image)
    if ref <= 1e-6:
        # More than 98% of the image is perfectly flat (a rendered or
        # saturated background around a small part): the floor sets the
        # scale, so every step of more than the floor is an edge.
        ref = floor_gradient / config.edge_high_frac

    # Canny on the gradient normalised by the image's own gradient scale keeps
    # the edge map independent of exposure and bit depth. Canny takes int16:
    # where the image is nearly blank (a part on a plain table fills less
    # than 2% of it) the scale is tiny and the part's edges would overflow,
    # so the scale is raised until the strongest gradient fits (clipped
    # gradients put their thresholds out of reach and bend their directions).
    norm = 1000.0 / ref
    full_scale = 1000.0
    if g_max * norm > 32000.0:
        shrink = 32000.0 / (g_max * norm)
        norm *= shrink
        full_scale *= shrink
    dx16, dy16 = scaled_int16(gx, gy, np.float32(norm), np.float32(32000.0))
    floor = floor_gradient * norm
    edges = np.asarray(cv2.Canny(
        dx16, dy16, max(config.edge_low_frac * full_scale, 0.5 * floor),
        max(config.edge_high_frac * full_scale, floor), L2gradient=True,
    ), np.uint8)
    if mask is not None:
        keep = cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        edges[~keep] = 0
    segment_mask = mask
    # Edge pixels are located and their gradient direction computed once,
    # before the texture test (which needs both); dropping texture pixels
    # from these lists keeps the raster order.
    pixel_xy = _edge_pixels(edges)
    pixel_index = pixel_xy[:, 1].astype(np.int64) * w + pixel_xy[:, 0]
    direction = np.arctan2(gy.ravel()[pixel_index], gx.ravel()[pixel_index])
    strong = mag.ravel()[pixel_index] >= config.strong_edge_frac * ref
    if config.texture_other_density < 1.0:
        # A strong edge is never texture: a small part lying on faint texture
        # has the texture's edges of every orientation all round its outline
        # (novel bench set, a tee on wood: 265 of the 477 edge pixels near it
        # were dropped). AR_MSSD means, novel seeds 0-2 and hard seeds 0-4,
        # models learned with the change (the training views' features change
        # slightly): 0.728 / 0.862 -> 0.741 / 0.877 (every hard seed's
        # recognition at least 0.95), LM-O 0.103 -> 0.107.
        texture = _texture_flags((h, w), pixel_index, direction, config) & ~strong
        texture_index = pixel_index[texture]
        edges.ravel()[texture_index] = 0
        # LSD works on the grey image, not on the edge map: its segments in
        # textured areas (where hardly a pixel is 2 px from a texture edge)
        # go too.
        not_texture = np.ones((h, w), np.uint8)
        not_texture.ravel()[texture_index] = 0
        away = cv2.erode(not_texture, np.ones((5, 5), np.uint8)) > 0
        segment_mask = away if mask is None else (mask & away)
        untextured = ~texture
        pixel_xy = np.compress(untextured, pixel_xy, axis=0)
        direction = direction[untextured]
        strong = strong[untextured]
    # The edge map is final: its distance transform (OpenCV, without the GIL)
    # runs on another core while the arc candidates are traced and the
    # segments grouped.
    nearest_job = _POOL.submit(_nearest_edge_maps, edges) if len(pixel_xy) else None
    # Edge tangent is perpendicular to the gradient; modulo π for polarity.
    edge_theta = np.asarray((direction + np.pi / 2.0) % np.pi, np.float32)
    edge_xy = pixel_xy.astype(np.float32)

    bits = orientation_bits_map(edge_xy, edge_theta, (h, w), spread_px)
    strong_bits = orientation_bits_map(edge_xy[strong], edge_theta[strong], (h, w), spread_px)
    if lines is None:
        nearest, dist = _nearest_edge_result(nearest_job, edges)
        return ImageFeatures(edge_xy, edge_theta, np.zeros((0, 4), np.float32),
                             GroupedFeatures(*_no_parts()), bits, strong_bits, nearest, dist,
                             (h, w))
    start_circles = _arc_candidates(edges, config)
    segments = _segments(lines.result(), config, segment_mask)
    segment_parts = _group(segments, config)
    nearest, dist = _nearest_edge_result(nearest_job, edges)
    arcs = _arcs_on_edges(start_circles, edge_xy, edge_theta, nearest, dist, config)
    grouped = _concat_parts([*segment_parts, arcs])
    return ImageFeatures(edge_xy, edge_theta, segments, grouped, bits, strong_bits, nearest, dist,
                         (h, w))


def _edge_pixels(edges: NDArray[np.uint8]) -> NDArray[np.int32]:
    """Non-zero pixels of an edge map in raster order (that of ``np.nonzero``).

    Parameters
    ----------
    edges : (H, W) uint8
        Edge map.

    Returns
    -------
    (E, 2) int32
        ``x, y`` of each non-zero pixel, pixels.
    """
    # cv2.findNonZero scans in raster order like np.nonzero, at a third of
    # its cost on a 400x300 map.
    found = cv2.findNonZero(edges)
    if found is None:
        return np.zeros((0, 2), np.int32)
    return np.asarray(found, np.int32).reshape(-1, 2)


def _texture_flags(shape: tuple[int, int], pixel_index: NDArray[np.int64], direction: F32,
                   config: FeatureConfig) -> NDArray[np.bool_]:
    """Which edge pixels lie inside texture (surround suppression, as in
    Grigorescu, Petkov & Westenberg 2003, "Contour detection based on
    nonclassical receptive field inhibition").

    A part's outline has few edges of other orientations around it (a corner,
    a hole nearby), texture and print have many in every direction. Counting
    only *other* orientations keeps dense parallel outlines (the faces of a
    thin plate) and a circle larger than the window's reach.

    Parameters
    ----------
    shape : (H, W)
        Image size, pixels.
    pixel_index : (E,) int64
        Raster index ``y * W + x`` of every edge pixel (all of them: each
        counts in its neighbours' windows), no repeats.
    direction : (E,) float32
        Their gradient direction, radians (any range; taken modulo π).
    config : FeatureConfig
        ``texture_radius_px`` and ``texture_other_density``.

    Returns
    -------
    (E,) bool
        True at edge pixels to drop.
    """
    if len(pixel_index) == 0:
        return np.zeros(0, bool)
    n_bins = 8
    theta = np.mod(direction, np.pi)
    b = np.minimum((theta * (n_bins / np.pi)).astype(np.int64), n_bins - 1)
    radius = config.texture_radius_px
    counts = window_bin_counts(shape[0], shape[1], pixel_index, b, n_bins, radius)
    # Own orientation and its two neighbours (±22.5°) count as "same".
    rows = np.arange(len(b))
    same = counts[rows, b] + counts[rows, (b + 1) % n_bins] + counts[rows, (b - 1) % n_bins]
    other = counts.sum(axis=1) - same
    side = 2 * radius + 1
    return np.asarray(other > config.texture_other_density * side * side)


def _quantisation_step(image: NDArray[np.generic]) -> float:
    """One grey level in the [0, 1] intensity unit of :func:`to_grey_float`;
    0 for float images (no known quantisation)."""
    dtype = np.asarray(image).dtype
    if dtype == np.uint8:
        return 1.0 / 255.0
    if dtype == np.uint16:
        return 1.0 / 65535.0
    return 0.0


def _gradient(image: NDArray[np.generic], smooth_grey: F32) -> tuple[F32, F32]:
    """Gradient of the smoothed image; for colour, per pixel that of the
    channel where it is largest (:func:`viewloc_core.gradient.image_gradient`)."""
    arr = np.asarray(image)
    if arr.ndim == 3 and arr.shape[2] >= 3:
        # The intensity unit of to_grey_float: integer images scaled to
        # [0, 1], float images taken as they are.
        step = _quantisation_step(arr)
        colour = arr[:, :, :3].astype(np.float32)
        if step:
            colour *= np.float32(step)
        else:
            colour = np.nan_to_num(colour)
        smooth_colour = cv2.GaussianBlur(colour, (0, 0), 1.0)
        return image_gradient(np.asarray(smooth_colour, np.float32))
    return image_gradient(smooth_grey)


def orientation_bin(theta: NDArray[np.floating]) -> NDArray[np.int64]:
    """Orientation bin in 0..ORIENTATION_BINS-1 of angles modulo π."""
    t = np.mod(np.asarray(theta, dtype=np.float64), np.pi)
    return np.minimum((t / np.pi * ORIENTATION_BINS).astype(np.int64), ORIENTATION_BINS - 1)


def orientation_turn(angle_rad: NDArray[np.floating] | float) -> NDArray[np.int64]:
    """Orientation bins an in-plane rotation moves edges by, rounded to the nearest.

    In 0..ORIENTATION_BINS (a rotation of nearly π turns by all of them, the
    same as none); add to a bin modulo ORIENTATION_BINS.
    """
    turn = np.mod(np.asarray(angle_rad, dtype=np.float64), np.pi) / np.pi * ORIENTATION_BINS
    return np.floor(turn + 0.5).astype(np.int64)


def wanted_bits(bins: NDArray[np.integer]) -> NDArray[np.int64]:
    """Bits of orientation bins and of their two neighbours (±11.25°): what a
    sample of bin ``b`` accepts in the spread orientation map."""
    b = np.asarray(bins, dtype=np.int64)
    n = ORIENTATION_BINS
    return (1 << b) | (1 << ((b + 1) % n)) | (1 << ((b - 1) % n))


def orientation_bits_map(
    edge_xy: F32, edge_theta: F32, shape: tuple[int, int], spread_px: int
) -> NDArray[np.uint16]:
    """LINE-2D spread map: bit b set within ``spread_px`` of an edge of bin b.

    Parameters
    ----------
    edge_xy : (E, 2) float32
        Edge pixels.
    edge_theta : (E,) float32
        Their orientation modulo π.
    shape : (H, W)
        Image size.
    spread_px : int
        Chebyshev radius of the spreading.

    Returns
    -------
    (H, W) uint16
    """
    h, w = shape
    bit = (1 << orientation_bin(edge_theta)).astype(np.uint16)
    # OR-spreading (a dilation would take a max, not an OR) round the edge
    # pixels only: they are few.
    return spread_bits(edge_xy[:, 0].astype(np.int64), edge_xy[:, 1].astype(np.int64), bit, h, w,
                       max(spread_px, 0))


def _empty_features(shape: tuple[int, int]) -> ImageFeatures:
    return ImageFeatures(
        np.zeros((0, 2), np.float32), np.zeros(0, np.float32), np.zeros((0, 4), np.float32),
        GroupedFeatures(*_no_parts()), np.zeros(shape, np.uint16), np.zeros(shape, np.uint16),
        np.full(shape, -1, np.int32), np.full(shape, np.inf, np.float32), shape,
    )


#: One LSD detector per thread: OpenCV's detector keeps state between calls
#: and crashes the process when two threads use one (the service localizes
#: concurrent requests in a thread pool).
_LSD_PER_THREAD = threading.local()

#: Threads that run OpenCV work (LSD, the distance transform) beside the rest
#: of the extraction (two: concurrent requests of the service need not queue
#: behind one another's LSD). No job waits for another: none can deadlock.
_POOL = ThreadPoolExecutor(max_workers=2, thread_name_prefix="viewloc-features")


def _nearest_edge_maps(edges: NDArray[np.uint8]) -> tuple[NDArray[np.int32], F32]:
    """Nearest edge pixel of every pixel and its distance.

    Parameters
    ----------
    edges : (H, W) uint8
        Edge map (non-zero on edges), at least one edge.

    Returns
    -------
    nearest : (H, W) int32
        Index of the nearest edge pixel in the raster order of
        :func:`_edge_pixels`.
    distance : (H, W) float32
        Its distance, pixels.
    """
    # The transform measures the distance to zero pixels: the edges, as 0
    # among 255s (one OpenCV pass instead of a comparison and a conversion).
    off_edge = cv2.threshold(edges, 0, 255, cv2.THRESH_BINARY_INV)[1]
    distance, labels = cv2.distanceTransformWithLabels(
        off_edge, cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL)
    # DIST_LABEL_PIXEL numbers the zero pixels from 1 in raster order, so
    # label - 1 indexes the edge pixels.
    nearest = np.asarray(labels, np.int32)
    nearest -= 1
    return nearest, np.asarray(distance, np.float32)


def _nearest_edge_result(job: Future[tuple[NDArray[np.int32], F32]] | None,
                         edges: NDArray[np.uint8]) -> tuple[NDArray[np.int32], F32]:
    """The maps of :func:`_nearest_edge_maps` submitted as ``job`` (None when
    there is no edge: index -1 and infinite distance everywhere)."""
    if job is None:
        return np.full(edges.shape, -1, np.int32), np.full(edges.shape, np.inf, np.float32)
    if job.cancel():
        # Not started (the threads are busy with other requests): waiting
        # for them would be slower than computing here.
        return _nearest_edge_maps(edges)
    return job.result()


def _detect_lines(smooth_grey: F32) -> NDArray[np.float32] | None:
    """Raw LSD output for a smoothed grey image (None when it finds nothing)."""
    # LSD wants 8 bit: stretch between robust extremes so dim images keep edges.
    lo_v, hi_v = np.percentile(smooth_grey[::2, ::2], [1.0, 99.0])
    stretch = 255.0 / max(hi_v - lo_v, 1e-6)
    grey8 = np.clip((smooth_grey - lo_v) * stretch, 0, 255).astype(np.uint8)
    lsd = getattr(_LSD_PER_THREAD, "detector", None)
    if lsd is None:
        lsd = cv2.createLineSegmentDetector(cv2.LSD_REFINE_NONE)
        _LSD_PER_THREAD.detector = lsd
    lines = lsd.detect(grey8)[0]
    return None if lines is None else np.asarray(lines, np.float32)


def _segments(lines: NDArray[np.float32] | None, config: FeatureConfig,
              mask: NDArray[np.bool_] | None) -> F32:
    """Straight segments from LSD's output; (S, 4) float32 end points."""
    if lines is None:
        return np.zeros((0, 4), np.float32)
    seg = lines.reshape(-1, 4).astype(np.float32)
    length = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1])
    seg = seg[length >= config.min_segment_px]
    if mask is not None and len(seg):
        keep = cv2.dilate(mask.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
        mid = ((seg[:, :2] + seg[:, 2:]) / 2).astype(np.int64)
        h, w = mask.shape
        mid[:, 0] = np.clip(mid[:, 0], 0, w - 1)
        mid[:, 1] = np.clip(mid[:, 1], 0, h - 1)
        seg = seg[keep[mid[:, 1], mid[:, 0]]]
    return seg


_Parts = tuple[NDArray[np.int8], F32, F32, F32, F32]


def _group(seg: F32, config: FeatureConfig) -> list[_Parts]:
    """Junctions, U-junctions and parallel pairs from segments."""
    junctions, meeting_ends, vertex = _junctions(seg, config)
    xy, theta, scale, attrs = u_junctions(seg, meeting_ends, vertex)
    u_parts = (np.full(len(xy), KIND_U_JUNCTION, np.int8), xy, theta, scale, attrs)
    return [junctions, u_parts, _parallel_pairs(seg, config)]


def _concat_parts(parts: list[_Parts]) -> GroupedFeatures:
    return GroupedFeatures(
        np.concatenate([p[0] for p in parts]),
        np.concatenate([p[1] for p in parts]),
        np.concatenate([p[2] for p in parts]),
        np.concatenate([p[3] for p in parts]),
        np.concatenate([p[4] for p in parts]),
    )


def _no_parts() -> _Parts:
    return (
        np.zeros(0, np.int8), np.zeros((0, 2), np.float32), np.zeros(0, np.float32),
        np.zeros(0, np.float32), np.zeros((0, 2), np.float32),
    )


def _junctions(seg: F32, config: FeatureConfig) -> tuple[_Parts, NDArray[np.int64], F64]:
    """L-junctions: two segment ends that (nearly) meet at a corner.

    Returns
    -------
    parts : _Parts
        The junction features.
    meeting_ends : (J, 2) int64
        Per junction, the two segment ends that meet, as rows of the ends
        table ``[starts; ends]`` (``e < n``: start of segment ``e``, else end
        of segment ``e - n``).
    vertex : (J, 2) float64
        Corner position, pixels.
    """
    n = len(seg)
    none = (_no_parts(), np.zeros((0, 2), np.int64), np.zeros((0, 2)))
    if n < 2:
        return none
    ends = np.concatenate([seg[:, :2], seg[:, 2:]]).astype(np.float64)  # (2n, 2)
    length = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1]).astype(np.float64)
    owner = np.concatenate([np.arange(n), np.arange(n)])
    # Each end reaches as far as its own segment allows: the gap test below
    # takes the shorter segment's.
    reach = config.junction_gap_frac * length[owner] + config.junction_gap_px
    a, b = pairs_within(ends, reach, within_both=True)
    if len(a) == 0:
        return none
    sa, sb = owner[a], owner[b]
    ok = sa != sb
    # Rows of (N, 2) arrays are gathered with np.take and np.compress here
    # and below: numpy's fancy and boolean indexing of them is several times
    # slower.
    end_a, end_b = np.take(ends, a, axis=0), np.take(ends, b, axis=0)
    gap = np.linalg.norm(end_a - end_b, axis=1)
    ok &= gap <= (
        config.junction_gap_frac * np.minimum(length[sa], length[sb]) + config.junction_gap_px
    )
    a, b, sa, sb = a[ok], b[ok], sa[ok], sb[ok]
    end_a, end_b = np.compress(ok, end_a, axis=0), np.compress(ok, end_b, axis=0)
    if len(a) == 0:
        return none
    # Arm direction: from the meeting end towards the far end of each segment
    # (the other end of segment s is row s + n or s - n of ``ends``).
    far_a = np.take(ends, np.where(a < n, a + n, a - n), axis=0)
    far_b = np.take(ends, np.where(b < n, b + n, b - n), axis=0)
    ua = far_a - end_a
    ub = far_b - end_b
    ua /= np.linalg.norm(ua, axis=1, keepdims=True)
    ub /= np.linalg.norm(ub, axis=1, keepdims=True)
    cos = np.clip((ua * ub).sum(axis=1), -1.0, 1.0)
    opening = np.arccos(cos)
    lo = np.radians(config.min_junction_angle_deg)
    ok = (opening > lo) & (opening < np.pi - lo)
    sa, sb, opening, a, b = sa[ok], sb[ok], opening[ok], a[ok], b[ok]
    ua, ub = np.compress(ok, ua, axis=0), np.compress(ok, ub, axis=0)
    if len(sa) == 0:
        return none
    # Vertex: intersection of the two lines (solve p_a + t ua = p_b + u ub).
    pa, pb = np.compress(ok, end_a, axis=0), np.compress(ok, end_b, axis=0)
    det = ua[:, 0] * (-ub[:, 1]) - ua[:, 1] * (-ub[:, 0])
    rhs = pb - pa
    t = (rhs[:, 0] * (-ub[:, 1]) - rhs[:, 1] * (-ub[:, 0])) / det
    vertex = pa + t[:, None] * ua
    # The vertex must lie near both meeting ends.
    near = np.linalg.norm(vertex - pa, axis=1) <= 0.3 * length[sa] + config.junction_gap_px
    near &= np.linalg.norm(vertex - pb, axis=1) <= 0.3 * length[sb] + config.junction_gap_px
    # Order the arms so the turn from arm 1 to arm 2 is positive (y down):
    # the attributes and the bisector are then unambiguous.
    cross = ua[:, 0] * ub[:, 1] - ua[:, 1] * ub[:, 0]
    swap = cross < 0
    u1 = np.where(swap[:, None], ub, ua)
    u2 = np.where(swap[:, None], ua, ub)
    l1 = np.where(swap, length[sb], length[sa])
    l2 = np.where(swap, length[sa], length[sb])
    bis = u1 + u2
    theta = np.mod(np.arctan2(bis[:, 1], bis[:, 0]), 2 * np.pi)
    scale = np.sqrt(l1 * l2)
    attrs = np.stack([opening, np.log(l1 / l2)], axis=1)
    sel = near
    kept_vertex = np.compress(sel, vertex, axis=0)
    return (
        np.full(int(sel.sum()), KIND_JUNCTION, np.int8),
        kept_vertex.astype(np.float32),
        theta[sel].astype(np.float32),
        scale[sel].astype(np.float32),
        np.compress(sel, attrs, axis=0).astype(np.float32),
    ), np.stack([a[sel], b[sel]], axis=1).astype(np.int64), kept_vertex


def _parallel_pairs(seg: F32, config: FeatureConfig) -> _Parts:
    """Pairs of overlapping, nearly parallel segments (e.g. the two sides of a bar)."""
    n = len(seg)
    if n < 2:
        return _no_parts()
    p1 = seg[:, :2].astype(np.float64)
    p2 = seg[:, 2:].astype(np.float64)
    mid = (p1 + p2) / 2
    d = p2 - p1
    length = np.linalg.norm(d, axis=1)
    u = d / length[:, None]
    ang = np.mod(np.arctan2(u[:, 1], u[:, 0]), np.pi)
    # Midpoints of a valid pair are at most (separation + length) apart, and
    # the separation is limited to twice the longer segment below: within
    # sqrt(5) of the longer segment's length.
    first, second = pairs_within(mid, 2.5 * length, within_both=False)
    if len(first) == 0:
        return _no_parts()
    # The pairs' geometry in one compiled pass, in the pairs' order (as numpy
    # over all pairs it was a dozen temporaries of thousands of rows, 3 ms
    # of a 400x300 textured image's features); the angles and logs stay
    # numpy's, whose last bits numba's do not always reproduce.
    i, j, dirn, xy, sep, overlap = parallel_pair_parts(
        p1, p2, mid, length, u, ang, first, second,
        float(np.radians(config.parallel_max_angle_deg)))
    if len(i) == 0:
        return _no_parts()
    theta = np.mod(np.arctan2(dirn[:, 1], dirn[:, 0]), np.pi)
    attrs = np.stack([np.log(overlap / sep), np.log(length[i] / length[j]) * 0.0], axis=1)
    return (
        np.full(len(i), KIND_PARALLEL, np.int8),
        xy.astype(np.float32),
        theta.astype(np.float32),
        sep.astype(np.float32),
        attrs.astype(np.float32),
    )


#: Half window, in contour steps, of the tangent estimate along an edge chain.
_ARC_STEP = 3
#: Direction (radians) of each offset ``(dx, dy)`` between the chain points
#: ``_ARC_STEP`` ahead and behind a point (at most ``2 _ARC_STEP`` pixels each
#: way), at ``[dy + 2 _ARC_STEP, dx + 2 _ARC_STEP]``: numpy's arctan2, whose
#: last bit numba's atan2 does not always reproduce.
_STEP_DIRECTION = np.arctan2(*np.mgrid[-2 * _ARC_STEP:2 * _ARC_STEP + 1,
                                       -2 * _ARC_STEP:2 * _ARC_STEP + 1].astype(np.float64))
#: Turning (radians) between the tangents ``_ARC_STEP`` steps before and after a
#: point that marks it as a corner, a branch or the end of an open chain; a
#: circle turns that much only below ``7 / 0.85 ≈ 8`` px radius.
_ARC_CORNER_TURN = 0.85
#: Pieces a circle does not fit are cut into chunks of this many contour
#: points and refitted: an arc that runs smoothly into a straight line has no
#: corner to split at, but its chunks fit, and the refit on the edges
#: extends them to the whole arc.
_ARC_CHUNK = 24
#: Most candidate circles refitted on the edges per image (largest first).
_ARC_MAX_CANDIDATES = 64
#: Arcs covering at least this angle are closed circles: the middle of the arc
#: is undefined, and the orientation is taken from the surrounding edges.
_ARC_CLOSED = np.radians(330.0)


def _arc_candidates(edges: NDArray[np.uint8], config: FeatureConfig) -> F64:
    """Starting circles for the circular arcs on the edge map (the arcs are
    :func:`_arcs_on_edges` of these).

    The edge map, dilated by one pixel to bridge the gaps Canny leaves on
    steep curves, is traced into closed pixel chains (``cv2.findContours``
    runs along both sides of an open curve and turns back at its ends). The
    chains are cut at corners (large turning of the tangent) and circles
    fitted to the pieces by linear least squares; pieces no circle fits are
    cut into chunks and fitted again. The circles that fit well enough, less
    near-copies, are the candidates.

    Parameters
    ----------
    edges : (H, W) uint8
        Canny edge map (non-zero on edges).
    config : FeatureConfig

    Returns
    -------
    (K, 3) float64
        ``cx, cy, r`` of each starting circle, pixels, best supported first.
    """
    no_circles = np.zeros((0, 3))
    traced = cv2.dilate(edges, np.ones((3, 3), np.uint8))
    contours, _ = cv2.findContours(traced, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    min_points = 4 * _ARC_STEP + 8
    chains = [c.reshape(-1, 2) for c in contours if len(c) >= min_points]
    if not chains:
        return no_circles
    lengths = np.array([len(c) for c in chains], np.int64)
    x, y, piece, n_pieces = chain_pieces(np.concatenate(chains), lengths, _ARC_STEP,
                                         _STEP_DIRECTION, _ARC_CORNER_TURN, 10)
    if n_pieces == 0:
        return no_circles

    fit = fit_circles(x, y, piece, n_pieces)
    good = _circle_ok(fit, config, np.radians(30.0), 1.5)
    # Chunks of the pieces no circle fits.
    chunk_x, chunk_y, chunk, n_chunks = piece_chunks(x, y, piece, ~good, _ARC_CHUNK,
                                                     _ARC_CHUNK // 2)
    # Chunks are short: ask for more curvature, or a pixel jog in a straight
    # line fits a wide circle.
    cfit = fit_circles(chunk_x, chunk_y, chunk, n_chunks)
    cgood = _circle_ok(cfit, config, np.radians(45.0), 1.5)
    cand = np.concatenate([fit[good], cfit[cgood]])
    if len(cand) == 0:
        return no_circles

    # Every candidate is refitted on the edge pixels along its circle; pieces
    # of one circle converge on it and the duplicates are dropped at the end
    # (grouping the candidates first lets a loose fit lead a group astray).
    # Only near-copies (the two sides of one chain, 2 px apart on the
    # dilated map) are dropped here.
    cand = _prune_circles(cand[np.argsort(-cand[:, 4], kind="stable")], config, 2.5)
    cand = cand[np.isfinite(cand[:, 2])]
    # A contiguous copy: the refit kernels are compiled (and warmed up) for
    # C-ordered arrays; a column slice would compile another version at the
    # first request.
    return np.ascontiguousarray(cand[:_ARC_MAX_CANDIDATES, :3])


def _arcs_on_edges(circles: F64, edge_xy: F32, edge_theta: F32, nearest: NDArray[np.int32],
                   edge_distance: F32, config: FeatureConfig) -> _Parts:
    """Refit circles ``(cx, cy, r)`` on the edge pixels along them; the good ones as arcs.

    The edge pixels of a circle are found by walking round it in 1 px steps
    and looking up the nearest edge pixel of each step (cost proportional to
    the perimeter, not to the number of edges); those close to the circle and
    tangent to it are kept and the circle refitted, three times with a
    narrowing band. This gathers the whole circle (both sides of a chain,
    pieces split by occlusion or branches); a circle is kept when its pixels
    fit it well and cover a long enough run of it, and duplicates of one
    circle are dropped.

    Position, orientation and size are covariant under a 2D similarity:
    ``xy`` the centre, ``theta`` the direction from the centre to the middle
    of the arc, ``scale`` the radius; the attribute (the angular span) is
    invariant. Everything comes from edge geometry, so neither brightness nor
    the sign of the contrast enters.

    Parameters
    ----------
    circles : (K, 3) float64
        Starting circles ``cx, cy, r``, pixels (:func:`_arc_candidates`).
    edge_xy : (E, 2) float32
        The edge pixels.
    edge_theta : (E,) float32
        Their tangent orientation modulo π, radians.
    nearest, edge_distance : (H, W) int32, float32
        Index of the nearest edge pixel and its distance (pixels), per pixel.
    config : FeatureConfig

    Returns
    -------
    kind, xy, theta, scale, attrs as in :class:`GroupedFeatures`.
    """
    exy = edge_xy.astype(np.float64)
    ex, ey = exy[:, 0].copy(), exy[:, 1].copy()  # contiguous: faster to gather
    eth = edge_theta.astype(np.float64)
    max_tangent_error = np.radians(12.0)
    current = circles
    label = np.zeros(0, np.int64)
    use = np.zeros(0, np.int64)
    for band_px, band_frac in ((4.0, 0.08), (2.5, 0.03), (1.5, 0.01)):
        band = band_px + band_frac * current[:, 2]
        label, use, dx, dy = pixels_near_circles(current, band, config.arc_max_radius_px,
                                                 ex, ey, nearest, edge_distance)
        # Circles with too few pixels stay in place as empty sets.
        refit, label, use = refit_on_pixels(current, band, label, use, dx, dy,
                                            np.arctan2(dy, dx), ex, ey, eth,
                                            max_tangent_error, 8)
        if len(label) == 0:
            return _no_parts()
        current = _prune_circles(refit, config)
    # Two starting circles may converge on one circle: keep the best covered.
    return _dedupe_arcs(_arc_parts(np.take(exy, use, axis=0), label, current, exy, config))


def _prune_circles(fit: F64, config: FeatureConfig, tol_px: float = 1.5) -> F64:
    """Between refits: drop (radius ∞) circles with too few pixels for the
    shortest arc and all but the best supported of circles that converged
    together (pieces of one circle usually do), to save the next passes."""
    return prune_circles(fit, 0.3 * np.radians(config.arc_min_span_deg), tol_px)


def _dedupe_arcs(parts: _Parts) -> _Parts:
    """One arc per circle: the longest among those of about the same centre and radius."""
    kind, xy, theta, scale, attrs = parts
    if len(kind) < 2:
        return parts
    order = np.argsort(-attrs[:, 0] * scale, kind="stable")
    kept: list[int] = []
    for i in order:
        same = [
            j for j in kept
            if np.hypot(*(xy[i] - xy[j])) <= 0.1 * scale[j] + 1.5
            and abs(scale[i] - scale[j]) <= 0.05 * scale[j] + 1.5
        ]
        if not same:
            kept.append(int(i))
    sel = np.sort(np.array(kept, np.int64))
    return kind[sel], xy[sel], theta[sel], scale[sel], attrs[sel]


def _arc_parts(pts: F64, label: NDArray[np.int64], circles: F64, edge_xy: F64,
               config: FeatureConfig) -> _Parts:
    """Span and orientation of each labelled circle; the acceptable ones as features.

    ``pts`` are the pixels on each circle (``label`` its row of ``circles``,
    ``cx, cy, r, rms, n``), ``edge_xy`` all edge pixels (for closed circles).
    """
    cx, cy, r, rms = circles[:, 0], circles[:, 1], circles[:, 2], circles[:, 3]
    fits = (r >= config.arc_min_radius_px) & (r <= config.arc_max_radius_px)
    fits &= rms <= np.maximum(config.arc_max_rms_px, config.arc_max_rms_frac * r)
    use = fits[label]
    pts, label = np.compress(use, pts, axis=0), label[use]
    if len(pts) == 0:
        return _no_parts()
    # Angular coverage in bins about 2 px of arc long. The arc is the longest
    # run of occupied bins interrupted by short gaps only (Canny drops
    # pixels): a circle tangent to the two arms of a corner is covered near
    # both tangent points but not between them, and is no arc.
    n_bins = np.clip(np.rint(np.pi * np.where(fits, r, 0.0)), 12, 360).astype(np.int64)
    psi = np.mod(np.arctan2(pts[:, 1] - cy[label], pts[:, 0] - cx[label]), 2 * np.pi)
    status, theta, span = arc_runs(label, psi, n_bins, _ARC_CLOSED / (2 * np.pi),
                                   np.radians(config.arc_min_span_deg))
    circle = np.flatnonzero(status != NO_ARC)
    for c in np.flatnonzero(status == CLOSED_CIRCLE):
        theta[c] = _closed_circle_orientation(edge_xy, cx[c], cy[c], r[c])
        span[c] = 2 * np.pi
    return (
        np.full(len(circle), KIND_ARC, np.int8),
        np.stack([cx[circle], cy[circle]], axis=1).astype(np.float32),
        np.mod(theta[circle], 2 * np.pi).astype(np.float32),
        r[circle].astype(np.float32),
        np.stack([span[circle], np.zeros(len(circle))], axis=1).astype(np.float32),
    )


def _closed_circle_orientation(edge_xy: F64, cx: float, cy: float, r: float) -> float:
    """Orientation of a closed circle: towards the centroid of the edges around it.

    A full circle has no middle; the other edges within 1.6 radii (a hub, the
    crescent of a second disc behind it) are as covariant as the circle and
    give it a direction when they are not centred on it. Symmetric
    surroundings leave it undetermined: then straight up (−y), arbitrarily.
    """
    d = np.hypot(edge_xy[:, 0] - cx, edge_xy[:, 1] - cy)
    near = (d < 1.6 * r) & (np.abs(d - r) > 2.5)
    if near.any():
        v = np.compress(near, edge_xy, axis=0).mean(axis=0) - (cx, cy)
        if np.hypot(v[0], v[1]) > 0.05 * r:
            return float(np.arctan2(v[1], v[0]))
    return 1.5 * np.pi


def _circle_ok(fit: F64, config: FeatureConfig, min_span: float,
               rms_slack: float) -> NDArray[np.bool_]:
    """Fits within the radius range and ``rms_slack`` times the RMS bound whose
    chain covers ``min_span`` radians."""
    r, rms, n = fit[:, 2], fit[:, 3], fit[:, 4]
    with np.errstate(invalid="ignore", divide="ignore"):
        # Contour steps are 1 or √2 px: about 1.1 px of arc per point.
        span = 1.1 * n / r
        return np.asarray(
            (r >= config.arc_min_radius_px) & (r <= config.arc_max_radius_px)
            & (rms <= rms_slack * np.maximum(config.arc_max_rms_px, config.arc_max_rms_frac * r))
            & (span >= min_span)
        )
