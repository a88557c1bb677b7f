"""Compiled loops of the feature extractor against their array forms and geometry."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from viewloc_core.feature_kernels import (
    ARC,
    CLOSED_CIRCLE,
    NO_ARC,
    arc_runs,
    chain_pieces,
    fit_circles,
    parallel_pair_parts,
    piece_chunks,
    scaled_int16,
    stronger_gradient,
    strongest_channel,
)


def _opencv_strongest_channel(gx3: np.ndarray, gy3: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The per-channel OpenCV form the kernel must reproduce bit for bit."""
    gx, gy = gx3[:, :, 0].copy(), gy3[:, :, 0].copy()
    best = cv2.add(cv2.multiply(gx, gx), cv2.multiply(gy, gy))
    for c in range(1, gx3.shape[2]):
        cx, cy = gx3[:, :, c].copy(), gy3[:, :, c].copy()
        mag = cv2.add(cv2.multiply(cx, cx), cv2.multiply(cy, cy))
        stronger = cv2.compare(mag, best, cv2.CMP_GT)
        cv2.copyTo(cx, stronger, gx)
        cv2.copyTo(cy, stronger, gy)
        cv2.max(best, mag, best)
    return gx, gy


def test_strongest_channel_equals_the_opencv_form_with_ties_to_the_first():
    rng = np.random.default_rng(0)
    gx3 = rng.normal(size=(40, 50, 3)).astype(np.float32)
    gy3 = rng.normal(size=(40, 50, 3)).astype(np.float32)
    # Ties: channel 2 equal to channel 0 on the top half, with swapped sign.
    gx3[:20, :, 2] = -gx3[:20, :, 0]
    gy3[:20, :, 2] = gy3[:20, :, 0]
    got = strongest_channel(gx3, gy3)
    expected = _opencv_strongest_channel(gx3, gy3)
    np.testing.assert_array_equal(got[0], expected[0])
    np.testing.assert_array_equal(got[1], expected[1])


def test_the_stronger_of_two_gradients_is_the_stronger_channel_of_their_stack():
    # What the colour boundary's merge computed before: weight times the
    # second gradient in numpy, both stacked as channels, the first on ties.
    rng = np.random.default_rng(1)
    grad = rng.normal(size=(30, 40, 2)).astype(np.float32)
    gx = rng.normal(size=(30, 40)).astype(np.float32)
    gy = rng.normal(size=(30, 40)).astype(np.float32)
    weight = np.float32(0.7)
    # Ties: the weighted second gradient equal to the first, turned, on a band.
    gx[:10] = grad[:10, :, 1] / weight
    gy[:10] = -grad[:10, :, 0] / weight
    got = stronger_gradient(grad, gx, gy, weight)
    sx, sy = strongest_channel(np.dstack([grad[..., 0], weight * gx]),
                               np.dstack([grad[..., 1], weight * gy]))
    np.testing.assert_array_equal(got, np.dstack([sx, sy]))
    assert (got[:10] == grad[:10]).mean() > 0.2  # ties occur and go to the first
    assert not np.array_equal(got, grad)


def test_scaled_int16_equals_numpy_clip_and_cast():
    rng = np.random.default_rng(1)
    gx = rng.normal(scale=40.0, size=(30, 40)).astype(np.float32)
    gy = rng.normal(scale=40.0, size=(30, 40)).astype(np.float32)
    scale = 917.3
    dx, dy = scaled_int16(gx, gy, np.float32(scale), np.float32(32000.0))
    np.testing.assert_array_equal(dx, np.clip(gx * scale, -32000, 32000).astype(np.int16))
    np.testing.assert_array_equal(dy, np.clip(gy * scale, -32000, 32000).astype(np.int16))
    assert dx.min() == -32000 and dx.max() == 32000  # both clips reached


def test_circle_fit_finds_centre_and_radius_and_flags_lines_and_empty_sets():
    rng = np.random.default_rng(2)
    angle = rng.uniform(0.0, 2.0, 60)  # about 115° of arc
    x = np.concatenate([30.0 + 12.0 * np.cos(angle), np.arange(20.0)])
    y = np.concatenate([-5.0 + 12.0 * np.sin(angle), 3.0 + 0.5 * np.arange(20.0)])
    label = np.concatenate([np.zeros(60, np.int64), np.full(20, 2, np.int64)])
    fit = fit_circles(x, y, label, 3)
    np.testing.assert_allclose(fit[0, :3], (30.0, -5.0, 12.0), atol=1e-9)
    assert fit[0, 3] < 1e-9 and fit[0, 4] == 60
    np.testing.assert_array_equal(fit[1], (0.0, 0.0, np.inf, 0.0, 0.0))  # no points
    assert np.isinf(fit[2, 2]) and fit[2, 4] == 20  # collinear


def _step_direction(step: int) -> np.ndarray:
    reach = 2 * step
    return np.arctan2(*np.mgrid[-reach:reach + 1, -reach:reach + 1].astype(np.float64))


def _square_chain(x0: int, y0: int, side: int) -> np.ndarray:
    """Closed 8-connected chain round a square, clockwise from its corner."""
    top = [(x0 + k, y0) for k in range(side)]
    right = [(x0 + side, y0 + k) for k in range(side)]
    bottom = [(x0 + side - k, y0 + side) for k in range(side)]
    left = [(x0, y0 + side - k) for k in range(side)]
    return np.array(top + right + bottom + left, np.int32)


def test_chain_pieces_cut_a_square_at_its_corners_and_keep_a_circle_whole():
    square = _square_chain(5, 5, 30)
    contour = cv2.findContours(cv2.circle(np.zeros((100, 100), np.uint8), (50, 50), 30, 255, 1),
                               cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)[0][0].reshape(-1, 2)
    chains = np.concatenate([square, contour])
    lengths = np.array([len(square), len(contour)], np.int64)
    x, y, piece, n_pieces = chain_pieces(chains, lengths, 3, _step_direction(3), 0.85, 10)
    assert n_pieces == 5
    # Four straight sides, each without the points near its corners.
    for p in range(4):
        side_x, side_y = x[piece == p], y[piece == p]
        assert 15 <= len(side_x) < 30
        assert np.ptp(side_x) == 0 or np.ptp(side_y) == 0
    assert (piece == 4).sum() == len(contour)
    assert np.all(np.diff(piece) >= 0)


def test_piece_chunks_cut_only_the_chosen_pieces_and_drop_short_chunks():
    piece = np.repeat(np.arange(3), [50, 30, 20])
    x = np.arange(100.0)
    y = -x
    split = np.array([True, False, True])
    cx, cy, chunk, n_chunks = piece_chunks(x, y, piece, split, 24, 12)
    # Piece 0: chunks of 24, 24 and 2 (dropped); piece 2: one of 20.
    assert n_chunks == 3
    np.testing.assert_array_equal(np.bincount(chunk), [24, 24, 20])
    np.testing.assert_array_equal(cx, np.concatenate([np.arange(48.0), np.arange(80.0, 100.0)]))
    np.testing.assert_array_equal(cy, -cx)


@pytest.mark.parametrize("start_deg", [0.0, 300.0])
def test_arc_runs_gives_span_and_middle_of_an_arc_and_marks_closed_circles(start_deg):
    n_bins = np.array([120, 120, 120], np.int64)
    # Circle 0: a 150° arc (wrapping past 0 when it starts at 300°) with a
    # bridged 2-bin gap; circle 1: all round; circle 2: two short pieces.
    arc = np.radians(start_deg + np.delete(np.arange(0.0, 150.0, 1.0), [40, 41, 42, 43, 44]))
    full = np.radians(np.arange(0.0, 360.0, 2.0))
    pieces = np.radians(np.r_[np.arange(0.0, 20.0), np.arange(180.0, 200.0)])
    angle = np.mod(np.concatenate([arc, full, pieces]), 2 * np.pi)
    label = np.repeat(np.arange(3), [len(arc), len(full), len(pieces)])
    status, theta, span = arc_runs(label, angle, n_bins, 330.0 / 360.0, np.radians(80.0))
    assert list(status) == [ARC, CLOSED_CIRCLE, NO_ARC]
    assert span[0] == pytest.approx(np.radians(150.0))
    assert np.mod(theta[0], 2 * np.pi) == pytest.approx(np.radians((start_deg + 75.0) % 360.0))


def _numpy_parallel_pair_parts(p1, p2, mid, length, u, ang, i, j, max_angle_rad):
    """The whole-array form (over all pairs at once) the kernel must reproduce bit for bit."""
    dang = np.abs(ang[i] - ang[j])
    dang = np.minimum(dang, np.pi - dang)
    ok = dang <= max_angle_rad
    i, j = i[ok], j[ok]
    ui, uj = u[i], u[j].copy()
    uj *= np.sign(ui[:, 0] * uj[:, 0] + ui[:, 1] * uj[:, 1])[:, None]
    dirn = ui + uj
    dirn /= np.linalg.norm(dirn, axis=1, keepdims=True)
    dx, dy = dirn[:, 0], dirn[:, 1]
    normal = np.stack([-dy, dx], axis=1)
    dm = mid[j] - mid[i]
    sep = np.abs(dm[:, 0] * -dy + dm[:, 1] * dx)

    def along(p, k):
        return p[k, 0] * dx + p[k, 1] * dy

    a1, a2, b1, b2 = along(p1, i), along(p2, i), along(p1, j), along(p2, j)
    lo = np.maximum(np.minimum(a1, a2), np.minimum(b1, b2))
    hi = np.minimum(np.maximum(a1, a2), np.maximum(b1, b2))
    overlap = hi - lo
    ok = ((sep >= 3.0) & (overlap >= 0.5 * np.minimum(length[i], length[j]))
          & (sep <= 2.0 * np.maximum(length[i], length[j])))
    across = ((mid[i] + mid[j]) / 2 * normal).sum(axis=1)
    xy = dirn * ((lo + hi) / 2)[:, None] + normal * across[:, None]
    return i[ok], j[ok], dirn[ok], xy[ok], sep[ok], overlap[ok]


def test_parallel_pair_parts_equals_the_array_form_and_finds_a_bar():
    rng = np.random.default_rng(5)
    p1 = rng.uniform(0, 200, (60, 2))
    # Many nearly parallel segments, some exactly so, some crossing.
    turn = rng.choice([0.0, 0.02, 0.3, np.pi], 60) + rng.normal(0, 0.05, 60)
    p2 = p1 + rng.uniform(10, 60, 60)[:, None] * np.column_stack([np.cos(turn), np.sin(turn)])
    mid = (p1 + p2) / 2
    length = np.linalg.norm(p2 - p1, axis=1)
    u = (p2 - p1) / length[:, None]
    ang = np.mod(np.arctan2(u[:, 1], u[:, 0]), np.pi)
    i, j = np.triu_indices(60, 1)
    i, j = np.ascontiguousarray(i, np.int64), np.ascontiguousarray(j, np.int64)
    got = parallel_pair_parts(p1, p2, mid, length, u, ang, i, j, np.radians(10.0))
    expected = _numpy_parallel_pair_parts(p1, p2, mid, length, u, ang, i, j, np.radians(10.0))
    assert len(got[0]) > 20
    for g, e in zip(got, expected, strict=True):
        np.testing.assert_array_equal(g, e)
    # The two sides of a bar 8 px wide, one drawn backwards: their centre
    # line, 8 px apart, overlapping over the shorter side.
    p1 = np.array([[10.0, 20.0], [45.0, 28.0]])
    p2 = np.array([[50.0, 20.0], [15.0, 28.0]])
    mid = (p1 + p2) / 2
    length = np.linalg.norm(p2 - p1, axis=1)
    u = (p2 - p1) / length[:, None]
    ang = np.mod(np.arctan2(u[:, 1], u[:, 0]), np.pi)
    i, j, dirn, xy, sep, overlap = parallel_pair_parts(
        p1, p2, mid, length, u, ang, np.array([0]), np.array([1]), np.radians(10.0))
    assert i.tolist() == [0] and j.tolist() == [1]
    np.testing.assert_allclose(np.abs(dirn[0]), [1.0, 0.0])
    np.testing.assert_allclose(xy[0], [30.0, 24.0])
    assert sep[0] == pytest.approx(8.0) and overlap[0] == pytest.approx(30.0)


def test_warm_up_compiles_every_kernel_on_all_zero_inputs():
    """setup.sh compiles the kernels through warm_up, which calls each once
    on one-element arrays of zeros: none of them may raise there (a zero
    direction divided by its zero length did, before numpy's error model)."""
    from viewloc_core.feature_kernels import warm_up

    warm_up()
