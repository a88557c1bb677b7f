"""Edge-based features of one image (Pope & Lowe's hierarchy, DESIGN.md §2 step 3).

From a grey or colour image (8 or 16 bit) this extracts

- **edge samples**: oriented edge pixels ``(x, y, θ)``, dense, used to verify
  and refit alignments and by the pose refinement;
- **segments**: straight edge segments (LSD, Grompone von Gioi et al. 2010);
- **junctions**: pairs of segments meeting at a vertex (L-junctions/corners);
- **parallel pairs**: two overlapping, nearly parallel segments.

Every grouped feature has a position ``b = (x, y, θ, s)`` (pixels, radians,
pixels) and similarity-invariant attributes ``a``. No feature depends on
absolute brightness or on the sign of the contrast: orientations are taken
modulo π, detection thresholds are relative to the image's own gradient
statistics, so a light part on a dark table and a dark part on a light table
give the same features.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from viewloc_core.errors import InvalidImageError

F32 = NDArray[np.float32]

#: Orientation bins over [0, π) for the spread orientation maps (LINE-2D style).
ORIENTATION_BINS = 16

#: Feature kinds; a model feature only pairs with an image feature of its kind.
KIND_JUNCTION = 0
KIND_PARALLEL = 1


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
    """

    min_segment_px: float = 7.0
    junction_gap_frac: float = 0.25
    junction_gap_px: float = 3.0
    min_junction_angle_deg: float = 25.0
    parallel_max_angle_deg: float = 8.0
    edge_low_frac: float = 0.08
    edge_high_frac: float = 0.2


@dataclass(frozen=True, slots=True)
class GroupedFeatures:
    """Sparse features with position and attributes (one row per feature).

    Attributes
    ----------
    kind : (F,) int8
        KIND_JUNCTION or KIND_PARALLEL.
    xy : (F, 2) float32
        Position, pixels.
    theta : (F,) float32
        Orientation, radians in [0, 2π) (junction bisector) or [0, π) (parallel).
    scale : (F,) float32
        Size, pixels (junction: geometric mean of arm lengths; parallel pair:
        separation of the two lines).
    attrs : (F, 2) float32
        Similarity-invariant attributes. Junction: (opening angle in radians,
        log arm-length ratio). Parallel pair: (log overlap/separation,
        log length ratio).
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
        Junctions and parallel pairs.
    orientation_bits : (H, W) uint16
        Bit ``b`` set where an edge of orientation bin ``b`` lies within the
        spread radius (LINE-2D's spread map); for fast verification.
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
    if arr.shape[0] < 16 or arr.shape[1] < 16:
        raise InvalidImageError(f"image too small: {arr.shape[:2]}", "image")
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

    Returns
    -------
    ImageFeatures
    """
    grey = to_grey_float(image)
    h, w = grey.shape
    smooth = np.asarray(cv2.GaussianBlur(grey, (0, 0), 1.0), np.float32)
    gx, gy = _gradient(image, smooth)
    mag = cv2.magnitude(gx, gy)
    # A strided sample is plenty for a percentile and four times cheaper.
    ref = float(np.percentile(mag[::2, ::2], 98.0))
    if ref <= 1e-6:
        return _empty_features((h, w))

    # Canny on the gradient normalised by the image's own gradient scale keeps
    # the edge map independent of exposure and bit depth.
    norm = 1000.0 / ref
    dx16 = np.clip(gx * norm, -32000, 32000).astype(np.int16)
    dy16 = np.clip(gy * norm, -32000, 32000).astype(np.int16)
    edges = cv2.Canny(
        dx16, dy16, config.edge_low_frac * 1000.0, config.edge_high_frac * 1000.0,
        L2gradient=True,
    )
    if mask is not None:
        keep = cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        edges[~keep] = 0
    ys, xs = np.nonzero(edges)
    # Edge tangent is perpendicular to the gradient; modulo π for polarity.
    tangent = (np.arctan2(gy[ys, xs], gx[ys, xs]) + np.pi / 2.0) % np.pi
    edge_xy = np.stack([xs, ys], axis=1).astype(np.float32)
    edge_theta = tangent.astype(np.float32)

    # LSD wants 8 bit: stretch between robust extremes so dim images keep edges.
    lo_v, hi_v = np.percentile(smooth[::2, ::2], [1.0, 99.0])
    grey8 = np.clip((smooth - lo_v) * (255.0 / max(hi_v - lo_v, 1e-6)), 0, 255).astype(np.uint8)
    segments = _segments(grey8, config, mask)
    grouped = _group(segments, config)
    bits = orientation_bits_map(edge_xy, edge_theta, (h, w), spread_px)
    if len(edge_xy):
        # Labels of DIST_LABEL_PIXEL number the zero pixels in raster order,
        # the order of np.nonzero above, so label - 1 indexes edge_xy.
        dist, labels = cv2.distanceTransformWithLabels(
            (edges == 0).astype(np.uint8), cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL
        )
        nearest = (labels - 1).astype(np.int32)
    else:
        dist = np.full((h, w), np.inf, np.float32)
        nearest = np.full((h, w), -1, np.int32)
    return ImageFeatures(edge_xy, edge_theta, segments, grouped, bits, nearest, dist, (h, w))


def _gradient(image: NDArray[np.generic], smooth_grey: F32) -> tuple[F32, F32]:
    """Image gradient; for colour, per pixel that of the channel where it is largest.

    Taking the strongest channel (as LINE-MOD does) keeps edges between
    colours of equal brightness, which any single grey conversion loses.
    """
    arr = np.asarray(image)
    if arr.ndim == 3 and arr.shape[2] >= 3:
        scale = 1.0 / (255.0 if arr.dtype == np.uint8 else 65535.0)
        colour = cv2.GaussianBlur(arr[:, :, :3].astype(np.float32) * scale, (0, 0), 1.0)
        gx3 = cv2.Sobel(colour, cv2.CV_32F, 1, 0, ksize=3)
        gy3 = cv2.Sobel(colour, cv2.CV_32F, 0, 1, ksize=3)
        best = np.argmax(gx3 * gx3 + gy3 * gy3, axis=2)[:, :, None]
        return (
            np.asarray(np.take_along_axis(gx3, best, axis=2)[:, :, 0], np.float32),
            np.asarray(np.take_along_axis(gy3, best, axis=2)[:, :, 0], np.float32),
        )
    return (
        np.asarray(cv2.Sobel(smooth_grey, cv2.CV_32F, 1, 0, ksize=3), np.float32),
        np.asarray(cv2.Sobel(smooth_grey, cv2.CV_32F, 0, 1, ksize=3), np.float32),
    )


def orientation_bin(theta: NDArray[np.floating]) -> NDArray[np.int64]:
    """Orientation bin in 0..ORIENTATION_BINS-1 of angles modulo π."""
    t = np.mod(np.asarray(theta, dtype=np.float64), np.pi)
    return np.minimum((t / np.pi * ORIENTATION_BINS).astype(np.int64), ORIENTATION_BINS - 1)


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
    bits = np.zeros((h, w), np.uint16)
    if len(edge_xy) == 0:
        return bits
    xs = edge_xy[:, 0].astype(np.int64)
    ys = edge_xy[:, 1].astype(np.int64)
    b = orientation_bin(edge_theta)
    np.bitwise_or.at(bits, (ys, xs), (1 << b).astype(np.uint16))
    if spread_px <= 0:
        return bits
    # OR-spreading by shifted copies (dilation would take a max, not an OR).
    out = bits.copy()
    for dy in range(-spread_px, spread_px + 1):
        for dx in range(-spread_px, spread_px + 1):
            if dx == 0 and dy == 0:
                continue
            src = bits[max(0, -dy): h - max(0, dy), max(0, -dx): w - max(0, dx)]
            out[max(0, dy): h - max(0, -dy), max(0, dx): w - max(0, -dx)] |= src
    return out


def _empty_features(shape: tuple[int, int]) -> ImageFeatures:
    empty_grouped = GroupedFeatures(
        np.zeros(0, np.int8), np.zeros((0, 2), np.float32), np.zeros(0, np.float32),
        np.zeros(0, np.float32), np.zeros((0, 2), np.float32),
    )
    return ImageFeatures(
        np.zeros((0, 2), np.float32), np.zeros(0, np.float32), np.zeros((0, 4), np.float32),
        empty_grouped, np.zeros(shape, np.uint16), np.full(shape, -1, np.int32),
        np.full(shape, np.inf, np.float32), shape,
    )


#: One LSD detector per thread: OpenCV's detector keeps state between calls
#: and crashes the process when two threads use one (the service localizes
#: concurrent requests in a thread pool).
_LSD_PER_THREAD = threading.local()


def _segments(grey8: NDArray[np.uint8], config: FeatureConfig,
              mask: NDArray[np.bool_] | None) -> F32:
    """Straight segments by LSD; (S, 4) float32 end points."""
    lsd = getattr(_LSD_PER_THREAD, "detector", None)
    if lsd is None:
        lsd = cv2.createLineSegmentDetector(cv2.LSD_REFINE_NONE)
        _LSD_PER_THREAD.detector = lsd
    lines = lsd.detect(grey8)[0]
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


def _group(seg: F32, config: FeatureConfig) -> GroupedFeatures:
    """Junctions and parallel pairs from segments."""
    junctions = _junctions(seg, config)
    parallels = _parallel_pairs(seg, config)
    return GroupedFeatures(
        np.concatenate([junctions[0], parallels[0]]),
        np.concatenate([junctions[1], parallels[1]]),
        np.concatenate([junctions[2], parallels[2]]),
        np.concatenate([junctions[3], parallels[3]]),
        np.concatenate([junctions[4], parallels[4]]),
    )


_Parts = tuple[NDArray[np.int8], F32, F32, F32, F32]


def _no_parts() -> _Parts:
    return (
        np.zeros(0, np.int8), np.zeros((0, 2), np.float32), np.zeros(0, np.float32),
        np.zeros(0, np.float32), np.zeros((0, 2), np.float32),
    )


def _junctions(seg: F32, config: FeatureConfig) -> _Parts:
    """L-junctions: two segment ends that (nearly) meet at a corner."""
    n = len(seg)
    if n < 2:
        return _no_parts()
    ends = np.concatenate([seg[:, :2], seg[:, 2:]]).astype(np.float64)  # (2n, 2)
    length = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1]).astype(np.float64)
    owner = np.concatenate([np.arange(n), np.arange(n)])
    max_gap = config.junction_gap_frac * float(length.max()) + config.junction_gap_px
    pairs = cKDTree(ends).query_pairs(max_gap, output_type="ndarray")
    if len(pairs) == 0:
        return _no_parts()
    a, b = pairs[:, 0], pairs[:, 1]
    sa, sb = owner[a], owner[b]
    ok = sa != sb
    gap = np.linalg.norm(ends[a] - ends[b], axis=1)
    ok &= gap <= (
        config.junction_gap_frac * np.minimum(length[sa], length[sb]) + config.junction_gap_px
    )
    a, b, sa, sb = a[ok], b[ok], sa[ok], sb[ok]
    if len(a) == 0:
        return _no_parts()
    # Arm direction: from the meeting end towards the far end of each segment.
    far_a = ends[(a + n) % (2 * n)]
    far_b = ends[(b + n) % (2 * n)]
    ua = far_a - ends[a]
    ub = far_b - ends[b]
    ua /= np.linalg.norm(ua, axis=1, keepdims=True)
    ub /= np.linalg.norm(ub, axis=1, keepdims=True)
    cos = np.clip((ua * ub).sum(axis=1), -1.0, 1.0)
    opening = np.arccos(cos)
    lo = np.radians(config.min_junction_angle_deg)
    ok = (opening > lo) & (opening < np.pi - lo)
    a, b, sa, sb, ua, ub, opening = a[ok], b[ok], sa[ok], sb[ok], ua[ok], ub[ok], opening[ok]
    if len(a) == 0:
        return _no_parts()
    # Vertex: intersection of the two lines (solve p_a + t ua = p_b + u ub).
    pa, pb = ends[a], ends[b]
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
    return (
        np.full(int(sel.sum()), KIND_JUNCTION, np.int8),
        vertex[sel].astype(np.float32),
        theta[sel].astype(np.float32),
        scale[sel].astype(np.float32),
        attrs[sel].astype(np.float32),
    )


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
    # the separation is limited to twice the longer segment below.
    radius = 2.5 * float(length.max())
    pairs = cKDTree(mid).query_pairs(radius, output_type="ndarray")
    if len(pairs) == 0:
        return _no_parts()
    i, j = pairs[:, 0], pairs[:, 1]
    dang = np.abs(ang[i] - ang[j])
    dang = np.minimum(dang, np.pi - dang)
    ok = dang <= np.radians(config.parallel_max_angle_deg)
    i, j = i[ok], j[ok]
    if len(i) == 0:
        return _no_parts()
    # Common direction (align j's direction with i's before averaging).
    uj = u[j] * np.sign((u[i] * u[j]).sum(axis=1))[:, None]
    dirn = u[i] + uj
    dirn /= np.linalg.norm(dirn, axis=1, keepdims=True)
    normal = np.stack([-dirn[:, 1], dirn[:, 0]], axis=1)
    sep = np.abs(((mid[j] - mid[i]) * normal).sum(axis=1))
    # Overlap of the projections on the common direction.
    ai = np.sort(np.stack([(p1[i] * dirn).sum(1), (p2[i] * dirn).sum(1)], 1), 1)
    aj = np.sort(np.stack([(p1[j] * dirn).sum(1), (p2[j] * dirn).sum(1)], 1), 1)
    overlap = np.minimum(ai[:, 1], aj[:, 1]) - np.maximum(ai[:, 0], aj[:, 0])
    shorter = np.minimum(length[i], length[j])
    ok = (sep >= 3.0) & (overlap >= 0.5 * shorter) & (sep <= 2.0 * np.maximum(length[i], length[j]))
    if not ok.any():
        return _no_parts()
    i, j, dirn, normal, sep, overlap = i[ok], j[ok], dirn[ok], normal[ok], sep[ok], overlap[ok]
    ai, aj = ai[ok], aj[ok]
    centre_along = (np.maximum(ai[:, 0], aj[:, 0]) + np.minimum(ai[:, 1], aj[:, 1])) / 2
    centre_across = ((mid[i] + mid[j]) / 2 * normal).sum(axis=1)
    xy = dirn * centre_along[:, None] + normal * centre_across[:, None]
    theta = np.mod(np.arctan2(dirn[:, 1], dirn[:, 0]), np.pi)
    attrs = np.stack([np.log(overlap / sep), np.log(length[i] / length[j]) * 0.0], axis=1)
    return (
        np.full(len(i), KIND_PARALLEL, np.int8),
        xy.astype(np.float32),
        theta.astype(np.float32),
        sep.astype(np.float32),
        attrs.astype(np.float32),
    )
