"""The client's image upload: arrays reach the service's decoder unchanged."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from app.imaging import decode_image
from viewloc_client.image_upload import upload_file

_MAX_PIXELS = 10**8

_sizes = st.tuples(st.integers(1, 37), st.integers(1, 37))


@st.composite
def _pixel_arrays(draw: st.DrawFn) -> np.ndarray:
    h, w = draw(_sizes)
    kind = draw(st.sampled_from(["grey8", "rgb8", "grey16"]))
    shape = (h, w, 3) if kind == "rgb8" else (h, w)
    dtype = np.uint16 if kind == "grey16" else np.uint8
    return draw(arrays(dtype, shape))


@settings(max_examples=60, deadline=None)
@given(_pixel_arrays())
def test_an_array_is_decoded_by_the_service_as_it_was_sent(pixels: np.ndarray) -> None:
    # Odd widths exercise BMP's row padding; RGB order must survive BMP's BGR.
    name, data = upload_file(pixels, "scene.png")
    decoded = decode_image(data, "image", _MAX_PIXELS)
    assert decoded.dtype == pixels.dtype and decoded.shape == pixels.shape
    np.testing.assert_array_equal(decoded, pixels)
    assert name == ("scene.tif" if pixels.dtype == np.uint16 else "scene.bmp")


def test_frames_go_uncompressed() -> None:
    frame = np.random.default_rng(0).integers(0, 256, (48, 64, 3), dtype=np.uint8)
    _, data = upload_file(frame, "scene")
    assert data[:2] == b"BM" and len(data) >= frame.nbytes
    _, data16 = upload_file(frame[:, :, 0].astype(np.uint16) * 257, "scene")
    assert data16[:4] in (b"II*\x00", b"MM\x00*") and len(data16) >= 48 * 64 * 2


def test_a_boolean_mask_is_sent_as_0_and_255() -> None:
    mask = np.zeros((5, 7), dtype=bool)
    mask[1:3, 2:6] = True
    _, data = upload_file(mask, "mask_0")
    np.testing.assert_array_equal(decode_image(data, "masks", _MAX_PIXELS), mask * np.uint8(255))


def test_files_and_bytes_are_sent_as_they_are(tmp_path: Path) -> None:
    path = tmp_path / "part.png"
    path.write_bytes(b"\x89PNG whatever")
    assert upload_file(path, "scene.png") == ("part.png", b"\x89PNG whatever")
    assert upload_file(str(path), "scene.png") == ("part.png", b"\x89PNG whatever")
    assert upload_file(b"abc", "scene.png") == ("scene.png", b"abc")
    assert upload_file(bytearray(b"abc"), "scene.png") == ("scene.png", b"abc")


@pytest.mark.parametrize("pixels", [
    np.zeros((4, 4, 4), np.uint8),    # alpha
    np.zeros((4, 4, 3), np.uint16),   # 16-bit colour
    np.zeros((4, 4), np.float32),
    np.zeros((0, 4), np.uint8),
    np.zeros((2, 4, 4, 3), np.uint8),
])
def test_other_arrays_are_refused_naming_the_parameter(pixels: np.ndarray) -> None:
    with pytest.raises(ValueError, match=r"^images\[2\]: an array must be"):
        upload_file(pixels, "image_2", "images[2]")


def test_other_types_are_refused() -> None:
    with pytest.raises(TypeError, match="^image: expected bytes"):
        upload_file(3.5, "scene")
