"""Feature extraction: kinds, invariance to brightness and bit depth, geometry."""

import cv2
import numpy as np
import pytest

from tests.viewloc_core.conftest import faint_noise
from viewloc_core.errors import InvalidImageError
from viewloc_core.features import (
    KIND_JUNCTION,
    KIND_PARALLEL,
    FeatureConfig,
    extract_features,
    orientation_bin,
)


def _square_image(value: int = 200, background: int = 30) -> np.ndarray:
    img = np.full((200, 240), background, np.uint8)
    cv2.rectangle(img, (60, 50), (170, 140), value, thickness=-1)
    return img


def test_square_gives_four_right_angle_junctions():
    feats = extract_features(_square_image())
    g = feats.grouped
    junctions = g.select(g.kind == KIND_JUNCTION)
    corners = np.array([[60, 50], [170, 50], [170, 140], [60, 140]], float)
    for corner in corners:
        d = np.linalg.norm(junctions.xy - corner, axis=1)
        assert d.min() < 3.0, corner
        near = d < 3.0
        assert np.all(np.abs(junctions.attrs[near, 0] - np.pi / 2) < np.radians(8))
    # Opposite sides of the square pair up as parallels.
    assert np.count_nonzero(g.kind == KIND_PARALLEL) >= 2


def test_edges_only_gives_the_same_edge_maps_and_nothing_else():
    # What the view search reads is the same; segments, junctions, pairs
    # and arcs are not extracted.
    image = _square_image()
    image[20:60, 90:110] = 120  # a second shape: more than one part
    full = extract_features(image)
    edges = extract_features(image, edges_only=True)
    for name in ("edge_xy", "edge_theta", "orientation_bits", "strong_bits", "nearest_edge",
                 "edge_distance"):
        assert np.array_equal(getattr(full, name), getattr(edges, name)), name
    assert len(full.segments) and len(full.grouped.kind)
    assert len(edges.segments) == 0 and len(edges.grouped.kind) == 0
    assert edges.shape == full.shape


def test_edges_do_not_depend_on_brightness_polarity_or_bit_depth():
    bright = extract_features(_square_image(200, 30))
    dark = extract_features(_square_image(30, 200))
    deep = extract_features(_square_image(200, 30).astype(np.uint16) * 257)
    dim = extract_features((_square_image(200, 30) // 8).astype(np.uint8))
    for other in (dark, deep, dim):
        assert abs(len(other.edge_xy) - len(bright.edge_xy)) <= 0.05 * len(bright.edge_xy)
        assert abs(len(other.grouped) - len(bright.grouped)) <= 2


def test_colour_edges_between_equal_luminance_colours_are_found():
    img = np.zeros((120, 160, 3), np.uint8)
    img[:, :80] = (200, 0, 0)
    img[:, 80:] = (0, 0, 200)
    feats = extract_features(img)
    assert len(feats.edge_xy) > 50
    # The edge is vertical: tangent orientation about π/2.
    assert np.median(np.abs(feats.edge_theta - np.pi / 2)) < 0.1


def test_float_colour_images_give_the_features_of_their_8_bit_original():
    # Colour in [0, 1] as float32: the same intensities as the uint8 image.
    # A dim, low-contrast one: the gradient of a float image was once scaled
    # as if it were 16 bit, and its edges fell under the blank-image threshold.
    grey = _square_image(45, 30)
    colour8 = np.dstack([grey, grey // 2, 60 - grey]).astype(np.uint8)
    colour_float = colour8.astype(np.float32) / np.float32(255.0)
    base = extract_features(colour8)
    floated = extract_features(colour_float)
    assert len(base.edge_xy) > 300
    assert abs(len(floated.edge_xy) - len(base.edge_xy)) <= 0.02 * len(base.edge_xy)
    assert abs(len(floated.grouped) - len(base.grouped)) <= 1


def test_junctions_rotate_with_the_image():
    img = _square_image()
    M = cv2.getRotationMatrix2D((120, 100), 30.0, 1.0)  # counter-clockwise on screen
    rotated = cv2.warpAffine(img, M, (240, 200), flags=cv2.INTER_LINEAR, borderValue=30)
    a = extract_features(img).grouped
    b = extract_features(rotated).grouped
    ja, jb = a.select(a.kind == KIND_JUNCTION), b.select(b.kind == KIND_JUNCTION)
    # A screen-counter-clockwise turn is a negative angle in y-down pixels.
    expected = np.mod(ja.theta - np.radians(30.0), 2 * np.pi)
    for th in expected:
        d = np.abs(np.mod(jb.theta - th + np.pi, 2 * np.pi) - np.pi)
        assert d.min() < np.radians(6)


def test_spread_orientation_map_marks_edge_neighbourhood():
    feats = extract_features(_square_image())
    horizontal = (1 << int(orientation_bin(np.array([0.0]))[0])) | (1 << 15)
    # Top side of the square (horizontal edge) at y = 49..50, spread by 2 px.
    assert feats.orientation_bits[48, 110] & horizontal
    assert feats.orientation_bits[51, 110] & horizontal
    assert feats.orientation_bits[100, 110] == 0


def test_nearest_edge_lookup():
    feats = extract_features(_square_image())
    found, idx = feats.nearest_edges(np.array([[110.0, 47.0], [110.0, 100.0]]), 4.0)
    assert found.tolist() == [True, False]
    assert abs(feats.edge_xy[idx[0], 1] - 50) <= 1.5


@pytest.mark.parametrize("bad", [np.zeros((8, 8), np.uint8), np.zeros((50, 50, 2), np.uint8),
                                 np.zeros((50, 50), np.int32)])
def test_rejects_unusable_images(bad):
    with pytest.raises(InvalidImageError):
        extract_features(bad)


def test_blank_image_has_no_features():
    feats = extract_features(np.full((64, 64), 128, np.uint8))
    assert len(feats.edge_xy) == 0 and len(feats.grouped) == 0


def test_concurrent_extraction_in_threads_is_safe_and_identical():
    """The service extracts features of concurrent requests in a thread pool;
    a detector shared between threads used to crash the process."""
    from concurrent.futures import ThreadPoolExecutor

    from viewloc_core.features import extract_features

    rng = np.random.default_rng(0)
    images = []
    for _ in range(4):
        img = np.full((240, 320), 40, np.uint8)
        for _ in range(30):
            p, q = rng.integers(0, [320, 240], size=(2, 2))
            cv2.line(img, tuple(map(int, p)), tuple(map(int, q)), int(rng.integers(90, 255)), 2)
        images.append(img)
    expected = [extract_features(im).segments for im in images]
    with ThreadPoolExecutor(max_workers=4) as pool:
        for _ in range(5):
            got = list(pool.map(lambda im: extract_features(im).segments, images))
            for a, b in zip(expected, got, strict=True):
                np.testing.assert_array_equal(a, b)


def _on_outline(feats, x0, y0, x1, y1, tol=2.0):
    """Edge pixels within ``tol`` of the rectangle's outline, and their count."""
    x, y = feats.edge_xy[:, 0], feats.edge_xy[:, 1]
    inside_x = (x > x0 - tol) & (x < x1 + tol)
    inside_y = (y > y0 - tol) & (y < y1 + tol)
    near_v = inside_y & ((np.abs(x - x0) <= tol) | (np.abs(x - x1) <= tol))
    near_h = inside_x & ((np.abs(y - y0) <= tol) | (np.abs(y - y1) <= tol))
    return near_v | near_h


def test_texture_edges_are_suppressed_and_the_outline_kept():
    rng = np.random.default_rng(3)
    # Turbulent two-tone texture (blurred noise, thresholded), a flat part on it.
    noise = cv2.GaussianBlur(rng.normal(size=(240, 320)).astype(np.float32), (0, 0), 1.0)
    img = np.where(noise > 0, 170, 120).astype(np.uint8)
    x0, y0, x1, y1 = 100, 70, 220, 170
    cv2.rectangle(img, (x0, y0), (x1, y1), 230, thickness=-1)
    from viewloc_core.features import FeatureConfig

    plain = extract_features(img, FeatureConfig(texture_other_density=1.0))
    kept = extract_features(img)
    outline_plain = _on_outline(plain, x0, y0, x1, y1)
    outline_kept = _on_outline(kept, x0, y0, x1, y1)
    # Most of the outline survives, most of the texture goes.
    assert outline_kept.sum() >= 0.6 * outline_plain.sum()
    assert (~outline_kept).sum() <= 0.3 * (~outline_plain).sum()


def test_texture_suppression_leaves_a_clean_image_alone():
    from viewloc_core.features import FeatureConfig

    img = _square_image()
    cv2.circle(img, (120, 95), 25, 90, thickness=-1)  # a hole: all orientations nearby
    plain = extract_features(img, FeatureConfig(texture_other_density=1.0))
    kept = extract_features(img)
    np.testing.assert_array_equal(plain.edge_xy, kept.edge_xy)
    assert len(kept.grouped) == len(plain.grouped)


def test_banding_of_a_smooth_gradient_is_not_an_edge():
    # A pale vertical ramp over 12 grey levels quantised to 8 bit: each step
    # is one grey level. With the object small, the 98th percentile of the
    # gradient is such a step; only the square's outline may become edges.
    h, w = 240, 320
    ramp = np.round(np.linspace(230.0, 242.0, w))[None, :].repeat(h, axis=0)
    img = ramp.astype(np.uint8)
    cv2.rectangle(img, (140, 100), (170, 130), 200, -1)
    feats = extract_features(img)
    assert len(feats.edge_xy) > 80
    x, y = feats.edge_xy[:, 0], feats.edge_xy[:, 1]
    on_square = (x >= 136) & (x <= 174) & (y >= 96) & (y <= 134)
    assert on_square.all()


@pytest.mark.parametrize("radius", [3, 12, 40])
def test_texture_test_counts_other_orientations_in_the_window(radius):
    """The packed integer window counts against a plain count (reflected borders)."""
    from viewloc_core.features import FeatureConfig, _texture_flags

    rng = np.random.default_rng(radius)
    edges = ((rng.random((90, 120)) < 0.25) * 255).astype(np.uint8)
    gx = rng.normal(size=edges.shape).astype(np.float32)
    gy = rng.normal(size=edges.shape).astype(np.float32)
    config = FeatureConfig(texture_radius_px=radius, texture_other_density=0.156)
    ys, xs = np.nonzero(edges)
    got = np.zeros(edges.shape, bool)
    got[ys, xs] = _texture_flags(edges.shape, ys * edges.shape[1] + xs,
                                 np.arctan2(gy[ys, xs], gx[ys, xs]), config)
    theta = np.mod(np.arctan2(gy, gx), np.pi)
    bins = np.minimum((theta * (8 / np.pi)).astype(int), 7)
    on = np.pad(edges > 0, radius, mode="symmetric")
    padded_bins = np.pad(bins, radius, mode="symmetric")
    expected = np.zeros(edges.shape, bool)
    side = 2 * radius + 1
    for y, x in zip(*np.nonzero(edges), strict=True):
        win_on = on[y: y + side, x: x + side]
        diff = np.abs(padded_bins[y: y + side, x: x + side] - bins[y, x])
        other = win_on & (np.minimum(diff, 8 - diff) > 1)
        expected[y, x] = other.sum() > 0.156 * side * side
    np.testing.assert_array_equal(got, expected)
    assert 0 < expected.sum() < (edges > 0).sum()


def test_spread_map_sets_each_bin_within_the_square_radius():
    from viewloc_core.features import orientation_bits_map

    rng = np.random.default_rng(4)
    h, w = 30, 40
    flat = rng.choice(h * w, 25, replace=False)
    xy = np.stack([flat % w, flat // w], axis=1).astype(np.float32)
    theta = rng.uniform(0, np.pi, 25).astype(np.float32)
    bits = orientation_bits_map(xy, theta, (h, w), 2)
    expected = np.zeros((h, w), np.uint16)
    for (x, y), b in zip(xy.astype(int), orientation_bin(theta), strict=True):
        expected[max(0, y - 2): y + 3, max(0, x - 2): x + 3] |= np.uint16(1 << int(b))
    np.testing.assert_array_equal(bits, expected)


@pytest.mark.parametrize("noise_share", [0.0, 0.01])
def test_a_small_part_on_a_plain_background_keeps_its_whole_outline(noise_share):
    """A part filling under 2% of the image: the 98th percentile of the
    gradient is 0 (a flat background) or tiny (one grey level of noise in a
    few pixels), which must neither blank the image nor overflow Canny's
    int16 gradients; every side of the part is found, nothing else."""
    img = np.full((480, 640), 40, np.uint8)
    img[np.random.default_rng(0).random(img.shape) < noise_share] = 41
    img[200:260, 300:380] = 143
    feats = extract_features(img)
    x, y = feats.edge_xy[:, 0], feats.edge_xy[:, 1]
    sides = {"top": np.abs(y - 199.5) < 2.5, "bottom": np.abs(y - 259.5) < 2.5,
             "left": np.abs(x - 299.5) < 2.5, "right": np.abs(x - 379.5) < 2.5}
    for name, on_side in sides.items():
        assert np.count_nonzero(on_side) >= 50, name
    assert np.all((np.abs(x - 339.5) < 43) & (np.abs(y - 229.5) < 33))


def test_a_part_stands_out_as_strong_edges_from_faint_texture():
    """Strong edges: the outline of a contrasted square on a faint noise
    texture, not the texture (which gives edges of its own all over)."""
    img = faint_noise((200, 240), 4, 1.5, 120, 6)
    cv2.rectangle(img, (60, 50), (170, 140), 200, thickness=-1)
    feats = extract_features(img)
    # The strong map is a subset of the full one.
    assert not np.any(feats.strong_bits & ~feats.orientation_bits)
    outline = np.zeros((200, 240), bool)
    cv2.rectangle(outline.view(np.uint8), (60, 50), (170, 140), 1, thickness=1)
    away = cv2.dilate(outline.astype(np.uint8), np.ones((15, 15), np.uint8)) == 0
    # The texture has edges nearly everywhere, hardly any strong one; the
    # outline is strong along its length.
    assert np.mean(feats.orientation_bits[away] > 0) > 0.3
    assert np.mean(feats.strong_bits[away] > 0) < 0.03
    assert np.mean(feats.strong_bits[outline] > 0) > 0.9
    # On a plain background every edge is strong.
    plain = extract_features(_square_image())
    np.testing.assert_array_equal(plain.strong_bits, plain.orientation_bits)


def test_a_small_part_on_fine_texture_keeps_its_outline():
    """The texture test drops edge pixels with many edges of other
    orientations around them, but not strong ones: a small bright square on
    fine noise keeps all of its outline."""
    texture = faint_noise((200, 240), 4, 0.7, 100, 25)
    img = texture.copy()
    cv2.rectangle(img, (100, 80), (140, 120), 250, thickness=-1)
    feats = extract_features(img)
    outline = np.zeros((200, 240), np.uint8)
    cv2.rectangle(outline, (100, 80), (140, 120), 1, thickness=1)
    ys, xs = np.nonzero(outline)
    found, _ = feats.nearest_edges(np.stack([xs, ys], axis=1).astype(float), 1.5)
    assert found.mean() > 0.98
    # The texture alone is still suppressed, but for its strongest pixels.
    unsuppressed = extract_features(texture, FeatureConfig(texture_other_density=1.0))
    assert len(extract_features(texture).edge_xy) < 0.1 * len(unsuppressed.edge_xy)
