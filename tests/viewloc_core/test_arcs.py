"""Circular-arc features: geometry, similarity covariance, lighting invariance, clutter."""

import cv2
import numpy as np
import pytest

from viewloc_core.features import KIND_ARC, GroupedFeatures, extract_features

BACKGROUND = 40
FOREGROUND = 190


def _noisy(img: np.ndarray, seed: int = 0) -> np.ndarray:
    """A frame near the border and mild sensor noise. The edge threshold is
    relative to the image's strongest 2% of gradients: with a lone small
    shape on a flat background those would be the noise."""
    framed = img.copy()
    h, w = img.shape
    cv2.rectangle(framed, (6, 6), (w - 7, h - 7), 120, 3)
    noise = np.random.default_rng(seed).normal(0.0, 1.0, img.shape)
    return np.clip(framed + noise, 0, 255).astype(np.uint8)


def _arcs(image: np.ndarray) -> GroupedFeatures:
    g = extract_features(image).grouped
    return g.select(g.kind == KIND_ARC)


def _cut_disc(centre=(150.0, 120.0), radius=50.0, cut=0.3, size=(240, 320)) -> np.ndarray:
    """A disc with the part right of ``cx + cut * r`` removed: an arc of
    ``360 - 2 acos(cut)`` degrees whose middle points left (θ = π)."""
    img = np.full(size, BACKGROUND, np.uint8)
    shift = 4  # sub-pixel drawing
    c = tuple(int(round(v * (1 << shift))) for v in centre)
    cv2.circle(img, c, int(round(radius * (1 << shift))), FOREGROUND, -1, cv2.LINE_AA, shift)
    img[:, int(round(centre[0] + cut * radius)):] = BACKGROUND
    return _noisy(img)


def _the_arc(arcs: GroupedFeatures, xy, radius) -> int:
    """Index of the arc nearest to the given centre and radius (which must exist)."""
    d = np.hypot(*(arcs.xy - np.asarray(xy, np.float32)).T) + np.abs(arcs.scale - radius)
    assert len(arcs) > 0 and d.min() < 5.0, (arcs.xy, arcs.scale)
    return int(np.argmin(d))


def _angle_diff(a: float, b: float) -> float:
    return abs((a - b + np.pi) % (2 * np.pi) - np.pi)


def test_full_circle_is_one_closed_arc_with_its_centre_and_radius():
    img = np.full((240, 320), BACKGROUND, np.uint8)
    cv2.circle(img, (170, 110), 45, FOREGROUND, -1, cv2.LINE_AA)
    arcs = _arcs(_noisy(img))
    i = _the_arc(arcs, (170, 110), 45)
    assert np.hypot(*(arcs.xy[i] - (170, 110))) < 1.0
    assert abs(arcs.scale[i] - 45) < 1.0
    assert arcs.attrs[i, 0] == pytest.approx(2 * np.pi)
    # One arc for the circle, none for the straight frame near the border.
    assert len(arcs) == 1


def test_partial_arc_has_centre_radius_span_and_direction():
    arcs = _arcs(_cut_disc())
    i = _the_arc(arcs, (150, 120), 50)
    assert np.hypot(*(arcs.xy[i] - (150, 120))) < 1.5
    assert abs(arcs.scale[i] - 50) < 1.5
    expected_span = 2 * np.pi - 2 * np.arccos(0.3)
    assert abs(arcs.attrs[i, 0] - expected_span) < np.radians(10)
    assert _angle_diff(float(arcs.theta[i]), np.pi) < np.radians(5)
    # The straight cut is no arc.
    assert len(arcs) == 1


@pytest.mark.parametrize("angle_deg, scale, shift", [(0.0, 1.0, (17.0, -9.0)),
                                                      (50.0, 1.0, (0.0, 0.0)),
                                                      (-120.0, 0.7, (10.0, 5.0)),
                                                      (200.0, 1.4, (-20.0, 12.0))])
def test_arcs_move_with_a_similarity_of_the_image(angle_deg, scale, shift):
    centre, radius = np.array([160.0, 120.0]), 40.0
    img = _cut_disc(tuple(centre), radius, cut=0.1)
    a = np.radians(angle_deg)
    # Rotation about the disc centre (y-down pixel angle), then scale and shift.
    R = scale * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    t = centre + np.asarray(shift) - R @ centre
    M = np.hstack([R, t[:, None]])
    moved = cv2.warpAffine(img, M, (320, 240), flags=cv2.INTER_LINEAR, borderValue=BACKGROUND)
    before = _arcs(img)
    after = _arcs(moved)
    i = _the_arc(before, centre, radius)
    j = _the_arc(after, R @ before.xy[i] + t, radius * scale)
    assert np.hypot(*(after.xy[j] - (R @ before.xy[i] + t))) < 1.5
    assert abs(after.scale[j] - scale * before.scale[i]) < 0.03 * scale * radius + 0.5
    assert _angle_diff(float(after.theta[j]), float(before.theta[i]) + a) < np.radians(5)
    assert abs(after.attrs[j, 0] - before.attrs[i, 0]) < np.radians(8)


def test_closed_circle_turns_towards_off_centre_structure():
    """A full circle's orientation comes from the edges around it (here an
    off-centre hole) and so rotates with the image."""
    def part(angle: float) -> np.ndarray:
        img = np.full((240, 320), BACKGROUND, np.uint8)
        cv2.circle(img, (160, 120), 50, FOREGROUND, -1, cv2.LINE_AA)
        hole = (160 + 25 * np.cos(angle), 120 + 25 * np.sin(angle))
        cv2.circle(img, tuple(int(round(v)) for v in hole), 10, BACKGROUND, -1, cv2.LINE_AA)
        return _noisy(img)

    for angle in np.radians([0.0, 100.0, 235.0]):
        arcs = _arcs(part(angle))
        i = _the_arc(arcs, (160, 120), 50)
        assert arcs.attrs[i, 0] == pytest.approx(2 * np.pi)
        assert _angle_diff(float(arcs.theta[i]), angle) < np.radians(5)


def test_arcs_do_not_depend_on_brightness_or_contrast_sign():
    img = _cut_disc()
    variants = [255 - img, (img // 5 + 20).astype(np.uint8), img.astype(np.uint16) * 257]
    ref = _arcs(img)
    for other in map(_arcs, variants):
        assert len(other) == len(ref)
        for i in range(len(ref)):
            j = _the_arc(other, ref.xy[i], ref.scale[i])
            assert np.hypot(*(other.xy[j] - ref.xy[i])) < 1.0
            assert abs(other.scale[j] - ref.scale[i]) < 1.0
            assert _angle_diff(float(other.theta[j]), float(ref.theta[i])) < np.radians(3)


def test_straight_line_clutter_gives_few_arcs():
    rng = np.random.default_rng(3)
    others = arcs = 0
    for _ in range(3):
        img = np.full((288, 384), 100, np.uint8)
        for _ in range(25):
            p, q = rng.integers(0, [384, 288], size=(2, 2))
            cv2.line(img, tuple(map(int, p)), tuple(map(int, q)), int(rng.integers(0, 255)),
                     int(rng.integers(1, 4)), cv2.LINE_AA)
        for _ in range(6):
            box = cv2.boxPoints(((float(rng.uniform(40, 340)), float(rng.uniform(40, 250))),
                                 (float(rng.uniform(15, 80)), float(rng.uniform(15, 80))),
                                 float(rng.uniform(0, 90))))
            cv2.fillConvexPoly(img, np.rint(box).astype(np.int32), int(rng.integers(0, 255)),
                               cv2.LINE_AA)
        g = extract_features(img).grouped
        others += int(np.count_nonzero(g.kind != KIND_ARC))
        arcs += int(np.count_nonzero(g.kind == KIND_ARC))
    # Lines crossing at shallow angles blend into short curves, so not none,
    # but an order of magnitude fewer than the features of straight lines.
    assert others > 300
    assert arcs <= 0.1 * others
