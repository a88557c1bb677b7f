"""Compiled per-pixel and per-point loops of the feature extractor.

As whole-array operations (OpenCV or numpy) each of these would take several
passes and temporaries. Each computes its values in the float precision and
order of those operations, so both forms agree to the last bit; where numba's
transcendental functions differ from numpy's in the last bit (atan2), the
caller passes numpy's results in.

:func:`warm_up` compiles them (or loads them from numba's cache).
"""

from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import NDArray

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

#: Status of a circle in :func:`arc_runs`.
NO_ARC = 0
ARC = 1
CLOSED_CIRCLE = 2


@njit(cache=True, nogil=True)
def strongest_channel(
    gx_channels: F32, gy_channels: F32
) -> tuple[F32, F32]:  # pragma: no cover - compiled
    """Per pixel, the gradient of the channel where its magnitude is largest.

    Parameters
    ----------
    gx_channels, gy_channels : (H, W, C) float32
        Gradient of each channel, intensity units per pixel.

    Returns
    -------
    gx, gy : (H, W) float32
        That of the channel with the largest squared magnitude
        ``gx² + gy²`` (each product and the sum rounded to float32, as
        OpenCV's multiply and add round them), the first one on ties.
    """
    h, w, n_channels = gx_channels.shape
    gx = np.empty((h, w), np.float32)
    gy = np.empty((h, w), np.float32)
    for i in range(h):
        for j in range(w):
            best_x = gx_channels[i, j, 0]
            best_y = gy_channels[i, j, 0]
            best_mag = best_x * best_x + best_y * best_y
            for c in range(1, n_channels):
                cx = gx_channels[i, j, c]
                cy = gy_channels[i, j, c]
                mag = cx * cx + cy * cy
                if mag > best_mag:
                    best_x, best_y, best_mag = cx, cy, mag
            gx[i, j] = best_x
            gy[i, j] = best_y
    return gx, gy


@njit(cache=True, nogil=True)
def stronger_gradient(grad: F32, gx: F32, gy: F32, weight: np.float32) -> F32:  # pragma: no cover
    """Per pixel, ``grad`` or ``weight`` times ``(gx, gy)``, whichever is the
    stronger: :func:`strongest_channel` of the two, ``grad`` first, written
    interleaved as ``grad`` is (no stacked copies of either).

    Parameters
    ----------
    grad : (H, W, 2) float32
        Interleaved (∂I/∂x, ∂I/∂y).
    gx, gy : (H, W) float32
        The other gradient, before ``weight``.
    weight : float32
        Factor on ``(gx, gy)`` (the product rounded to float32, as numpy's).

    Returns
    -------
    (H, W, 2) float32
    """
    h, w = gx.shape
    out = np.empty((h, w, 2), np.float32)
    for i in range(h):
        for j in range(w):
            ax = grad[i, j, 0]
            ay = grad[i, j, 1]
            bx = weight * gx[i, j]
            by = weight * gy[i, j]
            if bx * bx + by * by > ax * ax + ay * ay:
                out[i, j, 0] = bx
                out[i, j, 1] = by
            else:
                out[i, j, 0] = ax
                out[i, j, 1] = ay
    return out


@njit(cache=True, nogil=True)
def scaled_int16(
    gx: F32, gy: F32, scale: np.float32, limit: np.float32,
) -> tuple[NDArray[np.int16], NDArray[np.int16]]:  # pragma: no cover - compiled
    """``np.clip(g * scale, -limit, limit).astype(np.int16)`` of two planes in one pass.

    Parameters
    ----------
    gx, gy : (H, W) float32
        The planes.
    scale : float32
        Factor (the product is rounded to float32, as numpy's is).
    limit : float32
        Largest magnitude kept, at most 32767.

    Returns
    -------
    dx, dy : (H, W) int16
        Truncated towards zero.
    """
    h, w = gx.shape
    dx = np.empty((h, w), np.int16)
    dy = np.empty((h, w), np.int16)
    for i in range(h):
        for j in range(w):
            dx[i, j] = np.int16(min(max(gx[i, j] * scale, -limit), limit))
            dy[i, j] = np.int16(min(max(gy[i, j] * scale, -limit), limit))
    return dx, dy


@njit(cache=True, nogil=True)
def fit_circles(
    x: F64, y: F64, label: I64, n_sets: int
) -> F64:  # pragma: no cover - compiled
    """Algebraic (Kåsa) circle fit to every labelled point set at once.

    Parameters
    ----------
    x, y : (N,) float64
        Points, pixels.
    label : (N,) int64
        Set of each point, 0..n_sets-1.
    n_sets : int
        Number of sets.

    Returns
    -------
    (n_sets, 5) float64
        ``cx, cy, r, rms, n`` per set: centre and radius (pixels), RMS
        geometric distance of the points from the circle, point count. Sets
        on a line get an infinite radius, empty sets ``(0, 0, ∞, 0, 0)``.
    """
    # The sums run over the points in order, as np.bincount adds them, so
    # that the fits equal those of the array form to the last bit.
    n = np.zeros(n_sets)
    mx = np.zeros(n_sets)
    my = np.zeros(n_sets)
    for i in range(len(x)):
        n[label[i]] += 1.0
        mx[label[i]] += x[i]
        my[label[i]] += y[i]
    for s in range(n_sets):
        if n[s] > 0.0:
            mx[s] /= n[s]
            my[s] /= n[s]
    # Centred coordinates make the normal equations block diagonal:
    # u² + v² = A u + B v + C with C = mean(z) and a 2x2 system for (A, B).
    suu = np.zeros(n_sets)
    suv = np.zeros(n_sets)
    svv = np.zeros(n_sets)
    suz = np.zeros(n_sets)
    svz = np.zeros(n_sets)
    sz = np.zeros(n_sets)
    for i in range(len(x)):
        s = label[i]
        u = x[i] - mx[s]
        v = y[i] - my[s]
        z = u * u + v * v
        suu[s] += u * u
        suv[s] += u * v
        svv[s] += v * v
        suz[s] += u * z
        svz[s] += v * z
        sz[s] += z
    out = np.zeros((n_sets, 5))
    cu = np.zeros(n_sets)
    cv = np.zeros(n_sets)
    flat = np.zeros(n_sets, np.bool_)
    for s in range(n_sets):
        if n[s] == 0.0:
            out[s, 2] = np.inf
            continue
        det = suu[s] * svv[s] - suv[s] * suv[s]
        trace = suu[s] + svv[s]
        flat[s] = det <= 1e-9 * (trace * trace)
        if flat[s]:
            det = 1.0
        cu[s] = (svv[s] * suz[s] - suv[s] * svz[s]) / det / 2
        cv[s] = (suu[s] * svz[s] - suv[s] * suz[s]) / det / 2
        out[s, 0] = mx[s] + cu[s]
        out[s, 1] = my[s] + cv[s]
        out[s, 2] = np.sqrt(max(sz[s] / n[s] + cu[s] * cu[s] + cv[s] * cv[s], 0.0))
        out[s, 4] = n[s]
    # The residuals of the sets on a line are measured from their finite
    # fitted radius, made infinite only afterwards.
    sr = np.zeros(n_sets)
    for i in range(len(x)):
        s = label[i]
        resid = np.hypot(x[i] - mx[s] - cu[s], y[i] - my[s] - cv[s]) - out[s, 2]
        sr[s] += resid * resid
    for s in range(n_sets):
        if n[s] > 0.0:
            out[s, 3] = np.sqrt(sr[s] / n[s])
        if flat[s]:
            out[s, 2] = np.inf
    return out


@njit(cache=True, nogil=True)
def prune_circles(
    fit: F64, min_points_per_px: float, tol_px: float
) -> F64:  # pragma: no cover - compiled
    """Circles with too few points dropped, and near-copies of better ones.

    Parameters
    ----------
    fit : (K, 5) float64
        ``cx, cy, r, rms, n`` per circle (:func:`fit_circles`).
    min_points_per_px : float
        Circles with fewer than this many points per pixel of radius go.
    tol_px : float
        Circles whose centres and radii both differ by at most this much
        (pixels) are copies; the one with most points stays (the first on
        ties).

    Returns
    -------
    (K, 5) float64
        ``fit`` with the radius of the dropped circles set to infinity.
    """
    out = fit.copy()
    out[:, 2] = np.inf
    alive = np.flatnonzero(fit[:, 4] >= min_points_per_px * fit[:, 2])
    out[alive, 2] = fit[alive, 2]
    order = alive[np.argsort(-fit[alive, 4], kind="mergesort")]
    kept = np.empty(len(order), np.int64)
    n_kept = 0
    for i in order:
        copy = False
        for j in kept[:n_kept]:
            if (np.hypot(fit[j, 0] - fit[i, 0], fit[j, 1] - fit[i, 1]) <= tol_px
                    and abs(fit[j, 2] - fit[i, 2]) <= tol_px):
                copy = True
                break
        if copy:
            out[i, 2] = np.inf
        else:
            kept[n_kept] = i
            n_kept += 1
    return out


@njit(cache=True, nogil=True)
def pixels_near_circles(
    circles: F64, band_px: F64, max_radius_px: float, edge_x: F64, edge_y: F64,
    nearest: NDArray[np.int32], edge_distance: F32,
) -> tuple[I64, I64, F64, F64]:  # pragma: no cover - compiled
    """Edge pixels within a band of each circle, found by walking round it.

    Each circle is walked in ``ceil(2πr)`` equal steps; a step inside the
    image whose nearest edge pixel is within ``band_px + 1`` of it finds
    that pixel, unless it is the circle's previous find.

    Parameters
    ----------
    circles : (K, >=3) float64
        ``cx, cy, r`` per circle, pixels; those with infinite or larger than
        ``max_radius_px`` radius are skipped.
    band_px : (K,) float64
        Half-width of each circle's band, pixels.
    max_radius_px : float
        Largest radius walked, pixels.
    edge_x, edge_y : (E,) float64
        Edge pixel positions.
    nearest, edge_distance : (H, W) int32, float32
        Index of the nearest edge pixel and its distance (pixels), per pixel.

    Returns
    -------
    label : (M,) int64
        Circle of each find, in increasing order.
    pixel : (M,) int64
        The edge pixel found, in walking order per circle.
    dx, dy : (M,) float64
        Its offset from the circle's centre, pixels.
    """
    h, w = nearest.shape
    n_circles = circles.shape[0]
    steps = np.zeros(n_circles, np.int64)
    for c in range(n_circles):
        r = circles[c, 2]
        if np.isfinite(r) and r <= max_radius_px:
            steps[c] = int(np.ceil(2 * np.pi * r))
    capacity = steps.sum()
    label = np.empty(capacity, np.int64)
    pixel = np.empty(capacity, np.int64)
    count = 0
    for c in range(n_circles):
        cx, cy, r = circles[c, 0], circles[c, 1], circles[c, 2]
        reach = band_px[c] + 1.0
        previous = -1
        for k in range(steps[c]):
            angle = 2 * np.pi * k / steps[c]
            u = int(np.rint(cx + r * np.cos(angle)))
            v = int(np.rint(cy + r * np.sin(angle)))
            if u < 0 or u >= w or v < 0 or v >= h or edge_distance[v, u] > reach:
                continue
            found = nearest[v, u]
            # Neighbouring steps often find the same pixel.
            if found == previous:
                continue
            previous = found
            label[count] = c
            pixel[count] = found
            count += 1
    label = label[:count]
    pixel = pixel[:count]
    dx = np.empty(count)
    dy = np.empty(count)
    for m in range(count):
        dx[m] = edge_x[pixel[m]] - circles[label[m], 0]
        dy[m] = edge_y[pixel[m]] - circles[label[m], 1]
    return label, pixel, dx, dy


@njit(cache=True, nogil=True)
def refit_on_pixels(
    circles: F64, band_px: F64, label: I64, pixel: I64, dx: F64, dy: F64,
    radial_angle: F64, edge_x: F64, edge_y: F64, edge_theta: F64,
    max_tangent_error: float, min_pixels: int,
) -> tuple[F64, I64, I64]:  # pragma: no cover - compiled
    """Circles refitted on the edge pixels found near them that lie on them.

    Parameters
    ----------
    circles : (K, >=3) float64
        ``cx, cy, r`` per circle, pixels.
    band_px : (K,) float64
        Largest distance of a pixel from its circle, pixels.
    label, pixel, dx, dy : (M,) int64, int64, float64, float64
        Finds of :func:`pixels_near_circles`.
    radial_angle : (M,) float64
        ``np.arctan2(dy, dx)``, radians (numpy's, whose last bit numba's
        atan2 does not always reproduce).
    edge_x, edge_y : (E,) float64
        Edge pixel positions.
    edge_theta : (E,) float64
        Their tangent orientation modulo π, radians.
    max_tangent_error : float
        Largest angle between a pixel's tangent and the circle's, radians.
    min_pixels : int
        Circles with fewer pixels on them are not refitted.

    Returns
    -------
    refit : (K, 5) float64
        :func:`fit_circles` of each circle's pixels; ``(0, 0, ∞, 0, 0)``
        for those not refitted.
    label, pixel : (M',) int64
        The pixels of the refitted circles and their circle.
    """
    n_circles = circles.shape[0]
    on_circle = np.zeros(len(label), np.bool_)
    count = np.zeros(n_circles, np.int64)
    for m in range(len(label)):
        c = label[m]
        off_circle = abs(np.hypot(dx[m], dy[m]) - circles[c, 2])
        # Edge tangents are modulo π.
        tangent_error = abs(np.mod(edge_theta[pixel[m]] - radial_angle[m], np.pi) - np.pi / 2)
        if off_circle <= band_px[c] and tangent_error < max_tangent_error:
            on_circle[m] = True
            count[c] += 1
    for m in range(len(label)):
        on_circle[m] = on_circle[m] and count[label[m]] >= min_pixels
    kept_label = label[on_circle]
    kept_pixel = pixel[on_circle]
    refit = fit_circles(edge_x[kept_pixel], edge_y[kept_pixel], kept_label, n_circles)
    return refit, kept_label, kept_pixel


@njit(cache=True, nogil=True)
def _relabel_large(raw: I64, n_raw: int, min_count: int) -> tuple[I64, int]:  # pragma: no cover
    """Sets with at least ``min_count`` members renumbered in order, others -1."""
    count = np.zeros(n_raw, np.int64)
    for s in raw:
        count[s] += 1
    new = np.full(n_raw, -1, np.int64)
    n_large = 0
    for s in range(n_raw):
        if count[s] >= min_count:
            new[s] = n_large
            n_large += 1
    return new[raw], n_large


@njit(cache=True, nogil=True)
def chain_pieces(
    chain_xy: NDArray[np.int32], chain_length: I64, step: int, step_direction: F64,
    corner_turn: float, min_points: int,
) -> tuple[F64, F64, I64, int]:  # pragma: no cover - compiled
    """Closed pixel chains cut at their corners into pieces.

    A point is a corner where the chain's direction ``step`` points ahead
    and ``step`` points behind differ by more than ``corner_turn``; corners
    are dropped and the points between two of them make a piece. Each chain
    is read from its first corner (from its first point when it has none) so
    that no piece wraps round.

    Parameters
    ----------
    chain_xy : (N, 2) int32
        Points of all chains, one after the other; consecutive points of a
        chain are 8-neighbours, and the last one neighbours the first.
    chain_length : (C,) int64
        Points of each chain, each more than ``2 step``.
    step : int
        Half window of the direction estimate, points.
    step_direction : (4 step + 1, 4 step + 1) float64
        Direction in radians of an offset ``(dx, dy)`` between chain
        points, at ``[dy + 2 step, dx + 2 step]``.
    corner_turn : float
        Turning that makes a corner, radians.
    min_points : int
        Smaller pieces are dropped.

    Returns
    -------
    x, y : (M,) float64
        The points of the pieces, pixels, in chain order.
    piece : (M,) int64
        Piece of each point, 0..P-1 in order.
    n_pieces : int
        P.
    """
    n = len(chain_xy)
    x = np.empty(n)
    y = np.empty(n)
    raw_piece = np.empty(n, np.int64)
    n_out = 0
    n_raw = 0
    start = 0
    reach = 2 * step
    for length in chain_length:
        direction = np.empty(length)
        for pos in range(length):
            ahead = start + (pos + step) % length
            behind = start + (pos - step) % length
            direction[pos] = step_direction[chain_xy[ahead, 1] - chain_xy[behind, 1] + reach,
                                            chain_xy[ahead, 0] - chain_xy[behind, 0] + reach]
        corner = np.empty(length, np.bool_)
        first = -1
        for pos in range(length):
            turn = direction[(pos + step) % length] - direction[(pos - step) % length]
            wrapped = np.mod(turn + np.pi, 2 * np.pi) - np.pi
            corner[pos] = abs(wrapped) > corner_turn
            if corner[pos] and first < 0:
                first = pos
        first = max(first, 0)
        for q in range(length):
            pos = (q + first) % length
            if q == 0 or corner[pos]:
                n_raw += 1
            if not corner[pos]:
                x[n_out] = chain_xy[start + pos, 0]
                y[n_out] = chain_xy[start + pos, 1]
                raw_piece[n_out] = n_raw - 1
                n_out += 1
        start += length
    piece, n_pieces = _relabel_large(raw_piece[:n_out], n_raw, min_points)
    large = piece >= 0
    return x[:n_out][large], y[:n_out][large], piece[large], n_pieces


@njit(cache=True, nogil=True)
def piece_chunks(
    x: F64, y: F64, piece: I64, split: NDArray[np.bool_], chunk_points: int, min_points: int,
) -> tuple[F64, F64, I64, int]:  # pragma: no cover - compiled
    """Some pieces cut into chunks of consecutive points.

    Parameters
    ----------
    x, y : (M,) float64
        Points of the pieces, pixels (:func:`chain_pieces`).
    piece : (M,) int64
        Piece of each point, in increasing order.
    split : (P,) bool
        The pieces to cut.
    chunk_points : int
        Points per chunk (the last of a piece may be shorter).
    min_points : int
        Smaller chunks are dropped.

    Returns
    -------
    x, y : (M',) float64
        The points of the chunks, pixels.
    chunk : (M',) int64
        Chunk of each point, 0..Q-1 in order.
    n_chunks : int
        Q.
    """
    members = np.flatnonzero(split[piece])
    raw_chunk = np.empty(len(members), np.int64)
    n_raw = 0
    current_piece = -1
    piece_start = 0
    current_key = -1
    for a in range(len(members)):
        m = members[a]
        if piece[m] != current_piece:
            # Every point of a cut piece is a member: its first is the first.
            current_piece = piece[m]
            piece_start = m
            current_key = -1
        key = (m - piece_start) // chunk_points
        if key != current_key:
            current_key = key
            n_raw += 1
        raw_chunk[a] = n_raw - 1
    chunk, n_chunks = _relabel_large(raw_chunk, n_raw, min_points)
    large = chunk >= 0
    return x[members][large], y[members][large], chunk[large], n_chunks


@njit(cache=True, nogil=True)
def _reflected(n: int, radius: int) -> I64:  # pragma: no cover - compiled
    """Index in ``0..n-1`` of each position ``-radius..n-1+radius`` (at
    ``position + radius``), mirrored at the borders as OpenCV's
    BORDER_REFLECT does (``cba|abc|cba``)."""
    index = np.empty(n + 2 * radius, np.int64)
    for k in range(len(index)):
        p = k - radius
        while p < 0 or p >= n:
            p = -p - 1 if p < 0 else 2 * n - p - 1
        index[k] = p
    return index


@njit(cache=True, nogil=True)
def _grouped_by_row(
    pixel_index: I64, height: int, width: int,
) -> tuple[I64, I64]:  # pragma: no cover - compiled
    """Pixels grouped by image row: those of row ``y`` are
    ``order[row_start[y]:row_start[y + 1]]`` (indices into ``pixel_index``)."""
    row_start = np.zeros(height + 1, np.int64)
    for index in pixel_index:
        row_start[index // width + 1] += 1
    row_start = np.cumsum(row_start)
    order = np.empty(len(pixel_index), np.int64)
    filled = row_start[:-1].copy()
    for e in range(len(pixel_index)):
        y = pixel_index[e] // width
        order[filled[y]] = e
        filled[y] += 1
    return order, row_start


@njit(cache=True, nogil=True)
def window_bin_counts(
    height: int, width: int, pixel_index: I64, pixel_bin: I64, n_bins: int, radius: int,
) -> NDArray[np.int32]:  # pragma: no cover - compiled
    """Per pixel, how many pixels of each bin lie in the square window round it.

    Parameters
    ----------
    height, width : int
        Image size, pixels.
    pixel_index : (E,) int64
        Raster index ``y * width + x`` of the binned pixels, no repeats.
    pixel_bin : (E,) int64
        Their bin, ``0..n_bins-1``.
    n_bins : int
        Number of bins.
    radius : int
        Half-size of the window, pixels; the window extends past the image
        borders into their mirror image (OpenCV's BORDER_REFLECT).

    Returns
    -------
    (E, n_bins) int32
        Counts in the window of each pixel (itself included).
    """
    # Separable sums with several bins packed into each int64: a count of at
    # most side² never carries into the next bin's bit field.
    side = 2 * radius + 1
    field = 1
    while (1 << field) <= side * side:
        field += 1
    per_channel = 63 // field
    n_channels = (n_bins + per_channel - 1) // per_channel
    channel = pixel_bin // per_channel
    unit = np.left_shift(1, field * (pixel_bin - channel * per_channel))
    column_of = pixel_index % width
    # Down the image, row by row: the sums over the window's rows of every
    # column (a running sum, updated by the binned pixels of the row that
    # enters and the row that leaves the window), and along the row the
    # prefix sums of those, from which each binned pixel of the row reads
    # its window's sum.
    order, row_start = _grouped_by_row(pixel_index, height, width)
    source_x = _reflected(width, radius)
    source_y = _reflected(height, radius)
    columns = np.zeros((n_channels, width), np.int64)
    for k in range(side):
        for e in order[row_start[source_y[k]]:row_start[source_y[k] + 1]]:
            columns[channel[e], column_of[e]] += unit[e]
    prefix = np.zeros((n_channels, width + side), np.int64)
    field_mask = (1 << field) - 1
    counts = np.empty((len(pixel_index), n_bins), np.int32)
    for y in range(height):
        if y > 0:
            enter, leave = source_y[y + side - 1], source_y[y - 1]
            for e in order[row_start[enter]:row_start[enter + 1]]:
                columns[channel[e], column_of[e]] += unit[e]
            for e in order[row_start[leave]:row_start[leave + 1]]:
                columns[channel[e], column_of[e]] -= unit[e]
        if row_start[y] == row_start[y + 1]:
            continue
        for c in range(n_channels):
            running = 0
            for k in range(width + side - 1):
                running += columns[c, source_x[k]]
                prefix[c, k + 1] = running
        for e in order[row_start[y]:row_start[y + 1]]:
            for b in range(n_bins):
                c = b // per_channel
                packed = prefix[c, column_of[e] + side] - prefix[c, column_of[e]]
                counts[e, b] = (packed >> (field * (b - c * per_channel))) & field_mask
    return counts


@njit(cache=True, nogil=True)
def spread_bits(
    x: I64, y: I64, bit: NDArray[np.uint16], height: int, width: int, spread_px: int,
) -> NDArray[np.uint16]:  # pragma: no cover - compiled
    """OR of each pixel's bit into the square round it (clipped to the image).

    Parameters
    ----------
    x, y : (E,) int64
        Pixels, inside the image.
    bit : (E,) uint16
        Their bits.
    height, width : int
        Image size, pixels.
    spread_px : int
        Chebyshev radius of the square, pixels (0: the pixel alone).

    Returns
    -------
    (height, width) uint16
    """
    out = np.zeros((height, width), np.uint16)
    for e in range(len(x)):
        for v in range(max(y[e] - spread_px, 0), min(y[e] + spread_px + 1, height)):
            for u in range(max(x[e] - spread_px, 0), min(x[e] + spread_px + 1, width)):
                out[v, u] |= bit[e]
    return out


@njit(cache=True, nogil=True)
def arc_runs(
    label: I64, angle: F64, n_bins: I64, closed_fraction: float, min_span: float,
) -> tuple[NDArray[np.int8], F64, F64]:  # pragma: no cover - compiled
    """The longest run of each circle's angular coverage, short gaps bridged.

    Each circle is cut into ``n_bins`` equal bins by angle; gaps of empty
    bins longer than ``max(2, round(0.06 n_bins))`` end runs.

    Parameters
    ----------
    label : (M,) int64
        Circle of each point.
    angle : (M,) float64
        Its direction from the circle's centre, radians in [0, 2π).
    n_bins : (K,) int64
        Bins per circle.
    closed_fraction : float
        A circle whose gaps are all short and whose occupied stretch (all
        but its longest gap) covers at least this share of it is closed.
    min_span : float
        Shorter runs, radians, are no arc; nor runs whose bins are less than
        60% occupied.

    Returns
    -------
    status : (K,) int8
        NO_ARC, ARC or CLOSED_CIRCLE.
    theta : (K,) float64
        Direction from the centre to the middle of the arc, radians (arcs
        only).
    span : (K,) float64
        Angle the arc covers, radians (arcs only).
    """
    n_circles = len(n_bins)
    occupied = np.zeros((n_circles, n_bins.max()), np.bool_)
    for m in range(len(label)):
        n = n_bins[label[m]]
        occupied[label[m], min(int(angle[m] / (2 * np.pi) * n), n - 1)] = True
    status = np.full(n_circles, NO_ARC, np.int8)
    theta = np.zeros(n_circles)
    span = np.zeros(n_circles)
    for c in range(n_circles):
        n = n_bins[c]
        o = np.flatnonzero(occupied[c, :n])
        if len(o) == 0:
            continue
        # Empty bins after each occupied one, round the circle.
        gap = np.empty(len(o), np.int64)
        gap[:-1] = o[1:] - o[:-1] - 1
        gap[-1] = o[0] + n - o[-1] - 1
        big = np.flatnonzero(gap > max(2, round(0.06 * n)))
        if len(big) == 0:
            # Closed (or nearly): the middle of the arc is undefined.
            if n - gap.max() < closed_fraction * n:
                big = np.array([np.argmax(gap)])
            else:
                status[c] = CLOSED_CIRCLE
                continue
        # Runs start after a big gap and end at the next big gap.
        best_bins = -1
        best_count = 0
        best_first = 0
        for i in range(len(big)):
            first = (big[i] + 1) % len(o)
            last = big[(i + 1) % len(big)]
            run_bins = (o[last] - o[first]) % n + 1
            if run_bins > best_bins:
                best_bins = run_bins
                best_count = (last - first) % len(o) + 1
                best_first = first
        arc_span = 2 * np.pi * best_bins / n
        if arc_span < min_span or best_count < 0.6 * best_bins:
            continue
        status[c] = ARC
        theta[c] = (o[best_first] + (best_bins - 1) / 2 + 0.5) * 2 * np.pi / n
        span[c] = min(arc_span, 2 * np.pi)
    return status, theta, span


# numpy's error model: a zero direction divides to NaN as in the array
# form, instead of raising.
@njit(cache=True, nogil=True, error_model="numpy")
def parallel_pair_parts(
    p1: F64, p2: F64, mid: F64, length: F64, u: F64, ang: F64, i: I64, j: I64,
    max_angle_rad: float,
) -> tuple[I64, I64, F64, F64, F64, F64]:  # pragma: no cover - compiled
    """The pairs of segments that overlap, nearly parallel, and their frame.

    Parameters
    ----------
    p1, p2, mid : (S, 2) float64
        Segment ends and midpoints, pixels.
    length : (S,) float64
    u : (S, 2) float64
        Unit directions ``(p2 - p1) / length``.
    ang : (S,) float64
        Direction angles modulo π, radians.
    i, j : (P,) int64
        Candidate pairs (midpoints near enough), in the order to keep.
    max_angle_rad : float
        Largest angle between the two segments of a pair.

    Returns
    -------
    i, j : (K,) int64
        The pairs kept, in the order given.
    dirn : (K, 2) float64
        Their common unit direction.
    xy : (K, 2) float64
        Centre of their overlap, midway between the lines, pixels.
    sep : (K,) float64
        Distance between the two lines, pixels.
    overlap : (K,) float64
        Length of their overlap along ``dirn``, pixels.
    """
    n = len(i)
    keep_i = np.empty(n, np.int64)
    keep_j = np.empty(n, np.int64)
    dirn = np.empty((n, 2))
    xy = np.empty((n, 2))
    sep_out = np.empty(n)
    overlap_out = np.empty(n)
    k = 0
    for q in range(n):
        a, b = i[q], j[q]
        dang = abs(ang[a] - ang[b])
        dang = min(dang, np.pi - dang)
        if not dang <= max_angle_rad:
            continue
        # j's direction turned to agree with i's (the sign of their dot product).
        dot = u[a, 0] * u[b, 0] + u[a, 1] * u[b, 1]
        sign = 1.0 if dot > 0 else (-1.0 if dot < 0 else 0.0)
        dx = u[a, 0] + u[b, 0] * sign
        dy = u[a, 1] + u[b, 1] * sign
        norm = np.sqrt(dx * dx + dy * dy)
        dx /= norm
        dy /= norm
        sep = abs((mid[b, 0] - mid[a, 0]) * -dy + (mid[b, 1] - mid[a, 1]) * dx)
        a1 = p1[a, 0] * dx + p1[a, 1] * dy
        a2 = p2[a, 0] * dx + p2[a, 1] * dy
        b1 = p1[b, 0] * dx + p1[b, 1] * dy
        b2 = p2[b, 0] * dx + p2[b, 1] * dy
        lo = max(min(a1, a2), min(b1, b2))
        hi = min(max(a1, a2), max(b1, b2))
        overlap = hi - lo
        if not (sep >= 3.0 and overlap >= 0.5 * min(length[a], length[b])
                and sep <= 2.0 * max(length[a], length[b])):
            continue
        along = (lo + hi) / 2
        across = (mid[a, 0] + mid[b, 0]) / 2 * -dy + (mid[a, 1] + mid[b, 1]) / 2 * dx
        keep_i[k], keep_j[k] = a, b
        dirn[k, 0], dirn[k, 1] = dx, dy
        xy[k, 0] = dx * along + -dy * across
        xy[k, 1] = dy * along + dx * across
        sep_out[k], overlap_out[k] = sep, overlap
        k += 1
    return keep_i[:k], keep_j[:k], dirn[:k], xy[:k], sep_out[:k], overlap_out[:k]


def warm_up() -> None:
    """Compile (or load from numba's cache) for the types the extractor passes."""
    plane = np.zeros((1, 1, 3), np.float32)
    strongest_channel(plane, plane)
    pair = np.zeros((1, 1, 2), np.float32)
    stronger_gradient(pair, plane[..., 0].copy(), plane[..., 0].copy(), np.float32(1.0))
    grey = np.zeros((1, 1), np.float32)
    scaled_int16(grey, grey, np.float32(1.0), np.float32(1.0))
    one = np.zeros(1)
    index = np.zeros(1, np.int64)
    circles = prune_circles(fit_circles(one, one, index, 1), 1.0, 1.0)
    label, pixel, dx, dy = pixels_near_circles(circles, one, 1.0, one, one,
                                               np.zeros((1, 1), np.int32),
                                               np.zeros((1, 1), np.float32))
    refit_on_pixels(circles, one, label, pixel, dx, dy, dx, one, one, one, 1.0, 1)
    x, y, piece, _ = chain_pieces(np.zeros((1, 2), np.int32), np.ones(1, np.int64), 0,
                                  np.zeros((1, 1)), 1.0, 1)
    piece_chunks(x, y, piece, np.zeros(1, np.bool_), 1, 1)
    window_bin_counts(1, 1, index, index, 1, 1)
    spread_bits(index, index, np.ones(1, np.uint16), 1, 1, 1)
    arc_runs(index, one, np.full(1, 12, np.int64), 0.9, 1.0)
    ends = np.zeros((1, 2))
    parallel_pair_parts(ends, ends, ends, one, ends, one, index, index, 1.0)
