"""The part's own colour: where to look for it, and whether a fitted pose covers it.

Edges alone do not find a small part in a cluttered real photo: on LM-O
(real photos, parts of 50-80 px among dozens of other objects) the
alignment's locations missed the ape in all of 40 photos, while the view
search and refinement found it in 30 when given the true location. And where
a wrong place is fitted, its outline is confirmed about as well as the right
one's (refined inlier fractions 0.6-0.94 at both), so the contour cannot
decide. A part with colours of its own (a mesh with vertex colours or a
texture, real training photos with masks) says both where to look and which
fit covers the part.

Learning keeps a histogram of the part's chromaticity over its training
views. Localization back-projects the posterior P(part | colour) against the
scene's own colour distribution (Swain and Ballard's histogram
back-projection, ratio form), proposes the windows whose summed log ratio is
largest, and scores a fitted pose by the mean posterior under the surface
points it shows, which is compared with the mean posterior the part's own
colours get in that scene: a part of rare colours shows nearly 1, one of
colours common around it (dark, grey) about 0.5 however well it is fitted.

Chromaticity (r, g) = (R, G) / (R + G + B) is unchanged by the brightness of
the light and by shading, which move a part's colours most; dark pixels,
whose chromaticity is sensor noise, share one bin. The photos' white
balance differs from the renders': each training pixel is counted under a
few random per-channel gains (measured on LM-O with colours from the meshes:
the true location among the top 3 windows for 0.70 of the apes and 0.67 of
the cats, against 0.34 and 0.19 with hue-saturation bins).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from viewloc_core.colour_kernels import lookup_by_colour
from viewloc_core.errors import InvalidInputError

F32 = NDArray[np.float32]

#: Bins per chromaticity axis (r and g, each 0..1).
RG_BINS = 32

#: Pixels whose brightest channel is below this (0..255) are dark: one bin.
DARK_MAX_VALUE = 40

#: All bins: the chromaticity grid, then the dark bin.
N_BINS = RG_BINS * RG_BINS + 1

#: Gaussian blur of the histograms over the chromaticity grid, bins: a
#: colour seen in training spreads to its neighbours, as lights and sensors
#: move it.
HISTOGRAM_BLUR_BINS = 1.5

#: Per-channel gains drawn uniformly within 1 +- this, applied to training
#: pixels (white balance of the scene camera, tint of its lights).
WHITE_BALANCE_JITTER = 0.08

#: Gain triplets per training view (the first is neutral).
JITTER_DRAWS = 5

#: Training pixels binned per view, at most (an even subsample).
PIXELS_PER_VIEW = 4000

#: Fewest part pixels over all training views for a colour model.
MIN_PART_PIXELS = 500

#: Least :meth:`ColourAccumulator.view_agreement` for a colour model. A part
#: shows the same colours from every side, under every light: the LM-O
#: meshes' renders agree 0.98-1.00, photos of a part of one colour (rendered,
#: random lights and backdrops) 0.99. Photos of a part whose colour differs
#: from photo to photo (the hard set's scenes give their part a random
#: colour each) agree 0.72-0.73; the union of their colours is no colour of
#: the part's, and its proposals cost the hard set's parts learned from such
#: photos half their 2D recognitions (0.90 -> 0.38).
MIN_VIEW_AGREEMENT = 0.85

#: An image is grey (a monochrome camera's, stored as RGB) when fewer than
#: :data:`MIN_COLOURED_SHARE` of its pixels have channels further apart
#: than this (0..255).
GREY_CHANNEL_SPREAD = 12

#: A monochrome frame has no pixel of colour at all (its channels are equal,
#: or a few levels apart after compression), so any coherent share of
#: coloured pixels means a colour camera. The share must stay small: a small
#: coloured part on a neutral background (a conveyor, a grey table) is all
#: the colour such an image has. At 1 % the LM-O cat rendered at its true
#: poses on a plain grey background (84 px across, 0.5-1 % of the image
#: coloured) was taken as grey in 8 of 9 images: the features lost its
#: colour contrast and the cue its colours, and its depth came out 3-5 %
#: too far (1 of 9 within a tenth of its diameter); as colour 0.9-2 % (4 of
#: 9). The ape (0.35-1.1 % coloured, 9 of 10 taken as grey): 3 of 10 within
#: a tenth as grey, 4 of 10 as colour (depth -0.3 to +1.8 %).
MIN_COLOURED_SHARE = 0.001

#: Floor of every bin's probability, so that a colour missing from the
#: scene or from training cannot make the ratio explode.
PROBABILITY_FLOOR = 1e-4

#: Each pixel's log likelihood ratio is clipped to this range: one pixel is
#: weak evidence, and shadows, highlights and white balance move colours.
LOG_RATIO_RANGE = (-2.0, 3.0)


@functools.lru_cache(maxsize=1)
def _bin_table() -> NDArray[np.int32]:
    """Bin of every colour quantised to 6 bits per channel, (64**3,) int32."""
    q = np.arange(64, dtype=np.float64) * 4.0 + 2.0
    r, g, b = np.meshgrid(q, q, q, indexing="ij")
    total = r + g + b
    ri = np.minimum((r / total * RG_BINS).astype(np.int32), RG_BINS - 1)
    gi = np.minimum((g / total * RG_BINS).astype(np.int32), RG_BINS - 1)
    dark = np.maximum(np.maximum(r, g), b) < DARK_MAX_VALUE
    return np.where(dark, N_BINS - 1, ri * RG_BINS + gi).reshape(-1).astype(np.int32)


def _rgb_uint8(image: NDArray[np.generic]) -> NDArray[np.uint8] | None:
    """The RGB channels of a colour image as uint8; None for a grey image or
    one of floats (their unit is unknown, and images decoded from files are
    integers)."""
    arr = np.asarray(image)
    if arr.ndim != 3 or arr.shape[2] < 3:
        return None
    arr = arr[..., :3]
    if arr.dtype == np.uint16:
        return (arr >> 8).astype(np.uint8)
    if arr.dtype != np.uint8:
        return None
    return arr


def colour_bins(rgb: NDArray[np.uint8]) -> NDArray[np.int32]:
    """Histogram bin of each pixel.

    Parameters
    ----------
    rgb : (..., 3) uint8
        RGB colours.

    Returns
    -------
    (...) int32
        Bin index in ``0 .. N_BINS - 1``.
    """
    arr = np.asarray(rgb, np.uint8)
    # The compiled lookup takes an image: any other leading shape is one column.
    as_image = np.ascontiguousarray(arr.reshape(-1, 1, 3) if arr.ndim != 3 else arr)
    bins = lookup_by_colour(as_image, _bin_table())
    return np.asarray(bins, np.int32).reshape(arr.shape[:-1])


def _normalised(counts: NDArray[np.float64]) -> F32:
    """Blurred over the chromaticity grid and summed to 1, (N_BINS,) float32."""
    grid = cv2.GaussianBlur(counts[:-1].reshape(RG_BINS, RG_BINS).astype(np.float32), (0, 0),
                            HISTOGRAM_BLUR_BINS, borderType=cv2.BORDER_CONSTANT)
    out = np.concatenate([np.asarray(grid, np.float32).ravel(),
                          np.array([counts[-1]], np.float32)])
    total = float(out.sum())
    return (out / total).astype(np.float32) if total > 0 else out


class ColourAccumulator:
    """Collects the part's colours over its training views (learning).

    ``add`` each view with the part's mask; ``histogram`` gives the colour
    model, or None when the views showed too little of the part in colour or
    disagree about its colours (:data:`MIN_VIEW_AGREEMENT`).

    Parameters
    ----------
    seed : int
        Seed of the white-balance gains and the pixel subsample.
    """

    def __init__(self, seed: int = 0) -> None:
        self._counts = np.zeros(N_BINS, np.float64)
        self._pixels = 0
        # Each view's own counts (no jitter), for view_agreement.
        self._view_counts: list[NDArray[np.int64]] = []
        self._rng = np.random.default_rng(seed)

    def add(self, image: NDArray[np.generic], mask: NDArray[np.generic]) -> None:
        """Count the part's pixels in one view.

        Parameters
        ----------
        image : (H, W, 3) uint8 or uint16
            RGB; grey and float images add nothing.
        mask : (H, W) array
            Non-zero where the part is.
        """
        rgb = _rgb_uint8(image)
        if rgb is None:
            return
        part = np.asarray(mask) > 0
        if part.shape != rgb.shape[:2]:
            raise InvalidInputError("mask size differs from its image", "mask")
        pixels = rgb[part]
        if len(pixels) == 0:
            return
        if len(pixels) > PIXELS_PER_VIEW:
            pixels = pixels[self._rng.choice(len(pixels), PIXELS_PER_VIEW, replace=False)]
        self._pixels += len(pixels)
        # The first draw is neutral: the view's own colours, kept for view_agreement.
        neutral = np.bincount(colour_bins(pixels), minlength=N_BINS)
        self._view_counts.append(neutral)
        self._counts += neutral
        gains = 1.0 + self._rng.uniform(-WHITE_BALANCE_JITTER, WHITE_BALANCE_JITTER,
                                        (JITTER_DRAWS, 3))
        for gain in gains[1:]:
            jittered = np.clip(pixels * gain, 0.0, 255.0).astype(np.uint8)
            self._counts += np.bincount(colour_bins(jittered), minlength=N_BINS)

    def view_agreement(self) -> float:
        """How alike the views' colours are: the median over views of the
        Bhattacharyya coefficient of a view's histogram with all views' (0..1;
        0 before any view)."""
        if not self._view_counts:
            return 0.0
        whole = _normalised(self._counts)
        return float(np.median([np.sum(np.sqrt(_normalised(c.astype(np.float64)) * whole))
                                for c in self._view_counts]))

    def histogram(self) -> F32 | None:
        """(N_BINS,) float32 share of the part's pixels per bin (blurred), or
        None with under :data:`MIN_PART_PIXELS` pixels seen or views whose
        colours disagree (:data:`MIN_VIEW_AGREEMENT`)."""
        if self._pixels < MIN_PART_PIXELS or self.view_agreement() < MIN_VIEW_AGREEMENT:
            return None
        return _normalised(self._counts)


#: Pixels the grey test reads, about (an even grid, every 4th pixel each way
#: at least): the share of coloured pixels needs no more, and the test runs
#: on every request, whatever the camera's resolution.
GREY_TEST_PIXELS = 20_000


def _is_grey(rgb: NDArray[np.uint8]) -> bool:
    """Whether an RGB image shows no colours (see :data:`GREY_CHANNEL_SPREAD`)."""
    height, width = rgb.shape[:2]
    step = max(4, math.ceil(math.sqrt(height * width / GREY_TEST_PIXELS)))
    sample = rgb[::step, ::step]
    # Channel planes, not a reduction over the trailing axis of 3, which
    # costs ten times more (1.5 ms at 640x480).
    r, g, b = (np.asarray(sample[..., c], np.int16) for c in range(3))
    spread = np.maximum(np.maximum(r, g), b) - np.minimum(np.minimum(r, g), b)
    return bool(np.count_nonzero(spread > GREY_CHANNEL_SPREAD)
                < MIN_COLOURED_SHARE * spread.size)


def is_grey_in_colour(image: NDArray[np.generic]) -> bool:
    """Whether a colour image shows no colours: a monochrome camera's frame
    stored as RGB (or RGBA), or one whose channels differ by little more
    than noise (see :data:`GREY_CHANNEL_SPREAD`).

    Parameters
    ----------
    image : (H, W) or (H, W, C) array
        Any image.

    Returns
    -------
    bool
        True for an (H, W, 3|4) uint8 or uint16 image without colours; False
        for a grey (H, W) image, one with colours, and float images (whose
        unit is unknown).
    """
    rgb = _rgb_uint8(image)
    return rgb is not None and _is_grey(rgb)


def bin_log_ratios(image: NDArray[np.generic], histogram: F32,
                   ) -> tuple[NDArray[np.int32], F32] | None:
    """Each pixel's colour bin, and each bin's log likelihood ratio part
    against scene.

    Parameters
    ----------
    image : (H, W, 3) uint8 or uint16
        The scene, RGB.
    histogram : (N_BINS,) float32
        The part's colour model (:meth:`ColourAccumulator.histogram`).

    Returns
    -------
    ((H, W) int32, (N_BINS,) float32) or None
        The bins, and ``log P(colour | part) - log P(colour | scene)`` per
        bin clipped to :data:`LOG_RATIO_RANGE`; the scene's distribution is
        the image's own (the part covers a small share of it). None for a
        grey or float image, or a grey one stored as RGB.
    """
    rgb = _rgb_uint8(image)
    if rgb is None or _is_grey(rgb):
        return None
    bins = colour_bins(rgb)
    scene = _normalised(np.bincount(bins.ravel(), minlength=N_BINS).astype(np.float64))
    part = np.asarray(histogram, np.float32)
    if part.shape != (N_BINS,):
        raise InvalidInputError(f"colour histogram must have {N_BINS} bins", "model")
    ratio = (np.log(np.maximum(part, PROBABILITY_FLOOR))
             - np.log(np.maximum(scene, PROBABILITY_FLOOR)))
    lo, hi = LOG_RATIO_RANGE
    return bins, np.clip(ratio, lo, hi).astype(np.float32)


def log_ratio_map(image: NDArray[np.generic], histogram: F32) -> F32 | None:
    """Per-pixel log likelihood ratio, part against scene, of each pixel's
    colour (:func:`bin_log_ratios` looked up per pixel), (H, W) float32 or
    None for a grey or float image."""
    binned = bin_log_ratios(image, histogram)
    if binned is None:
        return None
    bins, ratio = binned
    return ratio[bins]


def expected_agreement(histogram: F32, ratio: F32) -> float:
    """The mean posterior P(part | colour) the part's own colours get in a
    scene: what :func:`agreement` gives the part itself when it shows its
    training colours.

    A part of distinctive colours gets nearly 1; one whose colours are
    common in the scene (dark, grey) about 0.5 or less, however well a pose
    covers it. Dividing an agreement by it puts parts and scenes on one
    scale.

    Parameters
    ----------
    histogram : (N_BINS,) float32
        The part's colour model.
    ratio : (N_BINS,) float32
        The scene's per-bin log ratios (:func:`bin_log_ratios`).

    Returns
    -------
    float in (0, 1)
    """
    part = np.asarray(histogram, np.float64)
    weights = part / max(float(part.sum()), 1e-12)
    return float(np.dot(weights, posterior(ratio).astype(np.float64)))


def posterior_map(image: NDArray[np.generic], bin_posterior: F32) -> F32 | None:
    """P(part | colour) of each pixel of ``image``, looked up per colour bin.

    Parameters
    ----------
    image : (H, W, 3) uint8 or uint16
        RGB.
    bin_posterior : (N_BINS,) float32
        The posterior of each bin (:func:`posterior` of the ratios
        :func:`bin_log_ratios` gives), e.g. from a pyramid level of the
        same scene.

    Returns
    -------
    (H, W) float32 or None
        None for a grey or float image.
    """
    rgb = _rgb_uint8(image)
    if rgb is None:
        return None
    table = np.asarray(bin_posterior, np.float32)
    if table.shape != (N_BINS,):
        raise InvalidInputError(f"bin posterior must have {N_BINS} bins", "bin_posterior")
    # One pass with the bins' values per quantised colour: the bins, then
    # the gather, cost up to twice as much.
    by_colour = np.ascontiguousarray(table[_bin_table()], np.float32)
    return np.asarray(lookup_by_colour(np.ascontiguousarray(rgb), by_colour), np.float32)


def posterior(log_ratio: F32) -> F32:
    """P(part | colour) with equal priors, from the log ratio, same shape, in (0, 1)."""
    return (1.0 / (1.0 + np.exp(-np.asarray(log_ratio, np.float32)))).astype(np.float32)


@dataclass(frozen=True, slots=True)
class ColourProposal:
    """An image window the part's colour explains.

    Attributes
    ----------
    x, y : float
        Window centre, pixels.
    half_size_px : float
        Half the side of the square window that explained it best, pixels.
    strength : float
        Sum of the pixels' clipped log likelihood ratios over the window,
        divided by its side (the square root of its pixel count).
    """

    x: float
    y: float
    half_size_px: float
    strength: float


def propose(log_ratio: F32, half_sizes_px: NDArray[np.floating], count: int,
            within: NDArray[np.floating] | None = None,
            exclusion_halves: float = 1.0) -> list[ColourProposal]:
    """The image windows whose colours the part explains best.

    Parameters
    ----------
    log_ratio : (H, W) float32
        From :func:`log_ratio_map`.
    half_sizes_px : (K,) array
        Half sides of the square windows tried, pixels.
    count : int
        Most proposals returned.
    within : (4,) array, optional
        ``x0, y0, x1, y1``: only windows centred in this rectangle (pixels)
        are proposed; their sums still read the pixels outside it.
    exclusion_halves : float
        Each proposal keeps later ones from being centred within this many
        of its window's half sides of its centre, on either axis (1: outside
        its window).

    Returns
    -------
    list of ColourProposal
        Best first, only windows with a positive sum; each centre lies
        outside the exclusion squares of the proposals before it.

    Notes
    -----
    Windows are compared by their sum of log ratios over the square root of
    their pixel count, as the sum's spread grows when the pixels are
    independent: a plain sum prefers windows larger than the part wherever
    its surroundings are slightly part-like, a mean prefers the smallest
    (LM-O, 60 photos each, window that found the part against the part's
    size: sum 1.27x for the ape; this 1.10x for the ape, 0.94x for the cat,
    1.14x for the can).
    """
    h, w = log_ratio.shape
    best = np.full((h, w), -np.inf, np.float32)
    best_half = np.zeros((h, w), np.float32)
    for half in np.asarray(half_sizes_px, np.float64):
        side = 2 * int(round(half)) + 1
        if side < 3:
            continue
        # Zero outside the image: a part cut by the border is still found.
        summed = cv2.boxFilter(log_ratio, cv2.CV_32F, (side, side), normalize=False,
                               borderType=cv2.BORDER_CONSTANT) / np.float32(side)
        better = summed > best
        best[better] = summed[better]
        best_half[better] = np.float32(half)
    if within is not None:
        x0, y0, x1, y1 = np.asarray(within, np.float64)
        rows, cols = np.arange(h), np.arange(w)
        best[(rows < y0) | (rows > y1), :] = -np.inf
        best[:, (cols < x0) | (cols > x1)] = -np.inf
    proposals: list[ColourProposal] = []
    for _ in range(max(count, 0)):
        flat = int(np.argmax(best))
        y, x = divmod(flat, w)
        value = float(best[y, x])
        if not np.isfinite(value) or value <= 0.0:
            break
        half = float(best_half[y, x])
        proposals.append(ColourProposal(float(x), float(y), half, value))
        r = max(1, int(round(exclusion_halves * half)))
        best[max(0, y - r):y + r + 1, max(0, x - r):x + r + 1] = -np.inf
    return proposals


def centroid(log_ratio: F32, x: float, y: float, radius_px: float,
             iterations: int = 3) -> tuple[float, float]:
    """Centre of the part-like colours around a point (mean shift).

    A window smaller than the part scores the same wherever it lies inside
    a part of one colour, so a proposal's centre may sit anywhere on it; the
    centroid of the positive log ratios in a disc as large as the part is
    near the part's middle.

    Parameters
    ----------
    log_ratio : (H, W) float32
        From :func:`log_ratio_map`.
    x, y : float
        Start, pixels.
    radius_px : float
        Radius of the disc, pixels (about half the part's image diameter).
    iterations : int
        Mean-shift steps.

    Returns
    -------
    (float, float)
        The centre, pixels; the start when the disc holds no positive ratio.
    """
    h, w = log_ratio.shape
    r = max(1, int(math.ceil(radius_px)))
    for _ in range(iterations):
        x0, x1 = max(0, int(round(x)) - r), min(w, int(round(x)) + r + 1)
        y0, y1 = max(0, int(round(y)) - r), min(h, int(round(y)) + r + 1)
        if x0 >= x1 or y0 >= y1:
            break
        yy, xx = np.mgrid[y0:y1, x0:x1]
        weight = np.maximum(log_ratio[y0:y1, x0:x1], 0.0)
        weight = weight * (((xx - x) ** 2 + (yy - y) ** 2) <= radius_px * radius_px)
        total = float(weight.sum())
        if total <= 0.0:
            break
        x, y = float((weight * xx).sum()) / total, float((weight * yy).sum()) / total
    return x, y


def agreement(part_posterior: F32, uv: NDArray[np.floating]) -> float | None:
    """Mean posterior of the part under image points (e.g. a pose's visible surface).

    Parameters
    ----------
    part_posterior : (H, W) float32
        From :func:`posterior`.
    uv : (M, 2) array
        Pixel positions in the map's frame; those outside it are skipped.

    Returns
    -------
    float in [0, 1] or None
        None when no point falls inside the map.
    """
    h, w = part_posterior.shape
    ij = np.rint(np.asarray(uv, np.float64)).astype(np.int64)
    inside = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
    if not inside.any():
        return None
    return float(part_posterior[ij[inside, 1], ij[inside, 0]].mean())
