"""Uploaded images: ``app.imaging.decode_image`` keeps the stored pixel grid; lens distortion
(``app.imaging.undistort`` and the from-images learning task that uses it)."""

from __future__ import annotations

import io
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image
from scipy.spatial import cKDTree

from app.imaging import (
    MAX_JPEG_SEGMENTS_BEFORE_FRAME,
    PILLOW_HEADER_BYTES,
    decode_image,
    header_size,
    undistort,
)
from app.jobs.tasks import learn_images
from model_store import ModelStore
from model_store.files import encode_arrays
from tests.app.helpers import jpeg
from tests.viewloc_core.conftest import l_bracket
from viewloc_core.camera import Camera
from viewloc_core.errors import InvalidImageError
from viewloc_core.pose import Pose
from viewloc_core.view_sphere import view_directions

DIST = (-0.5, 0.2, 0.001, -0.001, 0.0)
PINHOLE = Camera(400.0, 400.0, 159.5, 119.5, 320, 240)
LENS = Camera(400.0, 400.0, 159.5, 119.5, 320, 240, DIST)


def _distort(image: np.ndarray, camera: Camera, nearest: bool = False) -> np.ndarray:
    """What ``camera``'s lens makes of a pinhole image with the same K."""
    h, w = image.shape[:2]
    uu, vv = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    uv = np.stack([uu.ravel(), vv.ravel()], axis=1)[:, None, :]
    src = cv2.undistortPoints(uv, camera.K, np.array(camera.dist), P=camera.K)
    src = src.reshape(h, w, 2).astype(np.float32)
    flags = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    return cv2.remap(image, src[..., 0], src[..., 1], flags)


def test_undistort_inverts_the_lens_and_keeps_masks_binary() -> None:
    rng = np.random.default_rng(0)
    # A smooth pattern, so interpolation errors stay small against the lens's shift.
    pattern = cv2.GaussianBlur(rng.integers(0, 65535, (240, 320), endpoint=True)
                               .astype(np.uint16), (0, 0), 4)
    distorted = _distort(pattern, LENS)
    restored, cam = undistort(distorted, LENS)
    assert restored.dtype == np.uint16 and restored.shape == pattern.shape
    assert not cam.has_distortion and (cam.fx, cam.cx, cam.width) == (400.0, 159.5, 320)
    inner = (slice(40, 200), slice(50, 270))
    err_restored = np.abs(restored[inner].astype(float) - pattern[inner]).mean()
    err_distorted = np.abs(distorted[inner].astype(float) - pattern[inner]).mean()
    assert err_restored < 0.25 * err_distorted
    mask = np.zeros((240, 320), np.uint8)
    mask[60:180, 80:240] = 1
    m, _ = undistort(_distort(mask, LENS, nearest=True), LENS, nearest=True)
    assert set(np.unique(m).tolist()) <= {0, 1}
    assert np.mean(m[inner] != mask[inner]) < 0.01
    same, cam = undistort(pattern, PINHOLE)
    assert same is pattern and cam is PINHOLE


def _learn(tmp: Path, images: list[np.ndarray], masks: list[np.ndarray], camera: Camera,
           views: list[dict[str, float]]) -> object:
    store = ModelStore(tmp)
    arrays = {f"image_{i:04d}": a for i, a in enumerate(images)}
    arrays.update({f"mask_{i:04d}": m for i, m in enumerate(masks)})
    meta = {"count": len(images), "has_masks": True, "views": views, "diameter_mm": 130.0,
            "learning": {}, "camera": {"fx": camera.fx, "fy": camera.fy, "cx": camera.cx,
                                       "cy": camera.cy, "dist": list(camera.dist),
                                       "width": camera.width, "height": camera.height}}
    _, job = store.create_object(name="photos", source="images", kind="learn_images",
                                 upload=encode_arrays(arrays), upload_suffix="npz",
                                 upload_meta=meta, diameter_mm=130.0, training_views=len(images))
    return learn_images(store, job, lambda stage, fraction: None, lambda: False)


def test_learning_from_photos_through_a_lens_removes_the_distortion(tmp_path: Path) -> None:
    from viewloc_core.render import Renderer

    mesh = l_bracket()
    mesh.apply_translation(-np.asarray(mesh.bounds).mean(axis=0))
    pinhole: tuple[list[np.ndarray], list[np.ndarray]] = ([], [])
    lens: tuple[list[np.ndarray], list[np.ndarray]] = ([], [])
    views: list[dict[str, float]] = []
    with Renderer() as renderer:
        for v in view_directions(0):
            shot = renderer.render(mesh, PINHOLE, Pose(v.R_m2c, np.array([0.0, 0.0, 260.0])),
                                   background_rgb=(30, 30, 30))
            mask = shot.mask.astype(np.uint8)
            pinhole[0].append(shot.color)
            pinhole[1].append(mask)
            lens[0].append(_distort(shot.color, LENS))
            lens[1].append(_distort(mask, LENS, nearest=True))
            views.append({"azimuth_deg": v.azimuth_deg, "polar_deg": v.polar_deg,
                          "distance_mm": 260.0, "inplane_deg": 0.0})
    truth = _learn(tmp_path / "a", *pinhole, PINHOLE, views)
    with_dist = _learn(tmp_path / "b", *lens, LENS, views)
    ignoring = _learn(tmp_path / "c", *lens, PINHOLE, views)

    def edge_gap(model: object) -> float:
        """Mean distance of each view's edge samples to the pinhole-learned ones (px)."""
        ref = truth.training.edge_xy  # type: ignore[attr-defined]
        got = model.training.edge_xy  # type: ignore[attr-defined]
        return float(np.mean([cKDTree(a).query(b)[0].mean() for a, b in zip(ref, got,
                                                                             strict=True)]))

    assert edge_gap(with_dist) < 0.7 * edge_gap(ignoring)


def test_an_exif_orientation_tag_is_not_applied() -> None:
    # The intrinsics describe the stored pixel grid: a JPEG whose EXIF says
    # "turn 90 degrees" (orientation 6) decodes as stored, 60 wide, 40 high.
    stored = np.zeros((40, 60, 3), np.uint8)
    stored[:10, :20] = (255, 0, 0)
    exif = Image.Exif()
    exif[0x0112] = 6
    buf = io.BytesIO()
    Image.fromarray(stored).save(buf, format="JPEG", quality=95, exif=exif)
    assert Image.open(io.BytesIO(buf.getvalue())).getexif()[0x0112] == 6
    decoded = decode_image(buf.getvalue(), "image", 10_000)
    assert decoded.shape == (40, 60, 3)
    assert decoded[:10, :20, 0].mean() > 200 and decoded[30:, 40:, 0].mean() < 50


def _refusal(data: bytes, max_pixels: int = 10_000) -> InvalidImageError:
    """The error decode_image refuses ``data`` with (field "image")."""
    with pytest.raises(InvalidImageError) as info:
        decode_image(data, "image", max_pixels)
    assert info.value.field == "image"
    return info.value


def test_a_bomb_behind_a_stray_byte_is_refused_from_its_header() -> None:
    # 634 bytes whose frame header says 30000x30000; the stray byte after
    # APP0 made the header check give up, and decoding took 11 s and 3 GB.
    bomb = jpeg(16, 16, claimed_size=(30000, 30000), stray=b"\x00")
    # "W x H = N pixels" is the header check's wording; the check after
    # decoding does not multiply out.
    assert "30000x30000 = 900000000 pixels" in _refusal(bomb).message


@pytest.mark.parametrize("stray", [b"\x00", b"junk", b"\xff\x00", b"junk\xff\xff\xff"],
                         ids=["zero", "text", "stuffed-ff", "text-then-fill"])
def test_what_libjpeg_skips_between_segments_our_header_parser_skips(stray: bytes) -> None:
    plain, with_stray = jpeg(40, 30), jpeg(40, 30, stray=stray)
    assert header_size(with_stray, "jpeg") == (40, 30)
    decoded = decode_image(with_stray, "image", 10_000)
    assert decoded.shape == (30, 40, 3)
    np.testing.assert_array_equal(decoded, decode_image(plain, "image", 10_000))


def test_the_header_walk_stops_after_a_bounded_number_of_segments() -> None:
    # Empty comment segments (FF FE 00 02) before the frame header: valid,
    # and libjpeg reads them, but 8 million of them kept our walk busy 6-7 s.
    empty_comment = b"\xff\xfe\x00\x02"
    few = jpeg(40, 30, stray=empty_comment * 1_000)
    assert header_size(few, "jpeg") == (40, 30)
    beyond = MAX_JPEG_SEGMENTS_BEFORE_FRAME + 10
    many = jpeg(40, 30, stray=empty_comment * beyond)
    assert header_size(many, "jpeg") is None
    # Pillow sizes it from its first megabyte: still decoded.
    assert len(many) < PILLOW_HEADER_BYTES
    assert decode_image(many, "image", 10_000).shape == (30, 40, 3)
    # A frame header beyond that megabyte is sized by no one: refused undecoded.
    far = jpeg(40, 30, stray=empty_comment * (PILLOW_HEADER_BYTES // 4 + 10))
    assert _refusal(far).message == "the jpeg header does not give the image size"


def test_a_jpeg_whose_header_gives_no_size_is_refused_undecoded() -> None:
    data = jpeg(16, 16)
    sof = data.find(b"\xff\xc0")
    without_frame_header = data[:sof] + data[sof + 2 + int.from_bytes(data[sof + 2:sof + 4],
                                                                      "big"):]
    assert _refusal(without_frame_header).message == (
        "the jpeg header does not give the image size")


def _tiff_after_many_entries(width: int, height: int, pixels: bytes) -> bytes:
    """A grey 8-bit TIFF whose directory has 513 (repeated) NewSubfileType
    entries before the size, more than app.imaging's own parser reads;
    libtiff reads it with a warning (tags not sorted)."""
    entries = [(254, 4, 0)] * 513 + [(256, 3, width), (257, 3, height), (258, 3, 8),
                                     (259, 3, 1), (262, 3, 1), (273, 4, 0), (278, 3, height),
                                     (279, 4, len(pixels))]
    pixels_at = 8 + 2 + 12 * len(entries) + 4
    ifd = struct.pack("<H", len(entries)) + b"".join(
        struct.pack("<HHIHH" if typ == 3 else "<HHII", tag, typ, 1,
                    *((value, 0) if typ == 3 else (pixels_at if tag == 273 else value,)))
        for tag, typ, value in entries) + struct.pack("<I", 0)
    return b"II*\x00" + struct.pack("<I", 8) + ifd + pixels


def test_a_size_only_pillow_can_read_is_checked_and_kept() -> None:
    pixels = np.arange(24, dtype=np.uint8).reshape(4, 6) * 10
    small = _tiff_after_many_entries(6, 4, pixels.tobytes())
    np.testing.assert_array_equal(decode_image(small, "image", 10_000), pixels)
    bomb = _tiff_after_many_entries(30000, 30000, pixels.tobytes())
    assert "30000x30000 = 900000000 pixels" in _refusal(bomb).message


def _bmp(rgb: np.ndarray, header_bytes: int, top_down: bool = False) -> bytes:
    """A 24-bit BMP of ``rgb`` with a 12-byte OS/2 core header (16-bit
    sizes) or a 40-byte Windows info header (32-bit sizes, the height
    negative when ``top_down``)."""
    h, w = rgb.shape[:2]
    pad = b"\x00" * (-3 * w % 4)
    rows = range(h) if top_down else range(h - 1, -1, -1)
    pixels = b"".join(rgb[y, :, ::-1].tobytes() + pad for y in rows)
    if header_bytes == 12:
        dib = struct.pack("<IHHHH", 12, w, h, 1, 24)
    else:
        dib = struct.pack("<IiiHHIIiiII", 40, w, -h if top_down else h, 1, 24, 0, len(pixels),
                          2835, 2835, 0, 0)
    offset = 14 + len(dib)
    return b"BM" + struct.pack("<IHHI", offset + len(pixels), 0, 0, offset) + dib + pixels


def test_bmp_sizes_are_read_from_either_kind_of_header() -> None:
    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 255, (3, 5, 3), endpoint=True).astype(np.uint8)
    # The OS/2 core header's 16-bit sizes, read as 32-bit ones, made
    # 384x288 into 18874752x1572865 pixels and the image was refused.
    os2 = _bmp(rgb, 12)
    assert header_size(os2, "bmp") == (5, 3)
    # In colour: OpenCV reads a core-header BMP grey unless asked for colour.
    np.testing.assert_array_equal(decode_image(os2, "image", 10_000), rgb)
    for windows in (_bmp(rgb, 40), _bmp(rgb, 40, top_down=True)):
        assert header_size(windows, "bmp") == (5, 3)
        np.testing.assert_array_equal(decode_image(windows, "image", 10_000), rgb)
