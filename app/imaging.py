"""Decoding uploaded images (PNG, JPEG, TIFF, BMP; 8/16-bit; grey or colour).

The pixel count is read from the file header before anything is decoded, so
a small file that claims gigapixels (a decompression bomb) is refused without
allocating its pixels. A file whose header tells neither our parsers nor
Pillow its size is refused too: the decoder would find the size only by
allocating it.
"""

from __future__ import annotations

import io
import re
import struct
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from PIL import BmpImagePlugin, ImageFile, JpegImagePlugin, PngImagePlugin, TiffImagePlugin

# The from-images task's lens removal lives with the camera model; kept
# importable from here.
from viewloc_core.camera import undistort as undistort
from viewloc_core.errors import InvalidImageError

FORMATS = ("png", "jpeg", "tiff", "bmp")


def sniff_format(data: bytes) -> str | None:
    """Image format from the magic bytes, or None when it is not one we accept."""
    if data.startswith(b"\x89PNG\r\n\x1a\n"):
        return "png"
    if data.startswith(b"\xff\xd8\xff"):
        return "jpeg"
    if data.startswith((b"II*\x00", b"MM\x00*")):
        return "tiff"
    if data.startswith(b"BM"):
        return "bmp"
    return None


def _png_size(data: bytes) -> tuple[int, int] | None:
    if len(data) >= 24 and data[12:16] == b"IHDR":
        w, h = struct.unpack(">II", data[16:24])
        return int(w), int(h)
    return None


#: Length of the OS/2 BITMAPCOREHEADER, the one DIB header with 16-bit sizes.
_BMP_CORE_HEADER_BYTES = 12


def _bmp_header_bytes(data: bytes) -> int | None:
    """Length of a BMP file's DIB header (at offset 14, after the 14-byte
    file header), which tells the header's kind; None when cut short."""
    if len(data) < 18:
        return None
    return int(struct.unpack_from("<I", data, 14)[0])


def _bmp_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from the DIB header after the 14-byte file header.

    The header's own length (at offset 14) tells its kind: the 12-byte OS/2
    core header stores unsigned 16-bit sizes, the longer ones (OS/2 2.x, 16
    to 64 bytes; Windows, 40 bytes and up) signed 32-bit sizes, the height
    negative for rows stored top-down. Other lengths are no header at all.
    """
    header_bytes = _bmp_header_bytes(data)
    if header_bytes is None:
        return None
    if header_bytes == _BMP_CORE_HEADER_BYTES:
        w, h = struct.unpack_from("<HH", data, 18)
    elif header_bytes >= 16:
        w, h = struct.unpack_from("<ii", data, 18)
    else:
        return None
    return abs(int(w)), abs(int(h))


_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
#: Markers without a length: TEM, RST0-7 and (a repeated) SOI.
_STANDALONE = {0x01, 0xD8, *range(0xD0, 0xD8)}
_SOS, _EOI = 0xDA, 0xD9
#: A marker: 0xFF then a byte neither 0x00 (a stuffed 0xFF) nor 0xFF (fill).
#: Searching for it skips what libjpeg skips between segments: stray bytes
#: ("extraneous bytes before marker"), fill bytes and stuffed 0xFF 0x00.
_JPEG_MARKER = re.compile(rb"\xff[^\x00\xff]")


#: Segments read before the frame header, at most. Real files have a few
#: dozen (APPn, DQT, DHT, COM); a crafted 32 MB file of 8 million empty
#: ones kept the walk busy 6-7 s a request. Beyond this many the size is
#: left to Pillow, which is shown the first PILLOW_HEADER_BYTES only.
MAX_JPEG_SEGMENTS_BEFORE_FRAME = 65_536


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from the first frame header (SOF), found as libjpeg
    finds it; None past MAX_JPEG_SEGMENTS_BEFORE_FRAME segments."""
    i, n = 2, len(data)
    for _ in range(MAX_JPEG_SEGMENTS_BEFORE_FRAME):
        if i + 1 >= n:
            return None
        # The search only when something other than a marker sits here:
        # a crafted file of 8 million tiny segments took twice as long
        # with a search for each.
        if data[i] != 0xFF or data[i + 1] in (0x00, 0xFF):
            found = _JPEG_MARKER.search(data, i)
            if found is None:
                return None
            i = found.start()
        marker = data[i + 1]
        i += 2
        if marker in _STANDALONE:
            continue
        if marker in (_SOS, _EOI):
            return None  # libjpeg needs the frame header before the first scan
        # Cut short, these raise struct.error: header_size's None.
        (length,) = struct.unpack_from(">H", data, i)
        if marker in _SOF:
            h, w = struct.unpack_from(">HH", data, i + 3)
            return int(w), int(h)
        i += length
    return None


def _imread_flags(data: bytes, fmt: str) -> int:
    """How cv2.imdecode should read the file.

    UNCHANGED keeps 16-bit samples and, unlike IMREAD_COLOR, ignores an
    EXIF orientation tag: the camera's intrinsics describe the pixel grid as
    stored (README, "Image size"). An OS/2 core-header BMP is read as COLOR
    (a BMP has neither 16-bit samples nor EXIF): OpenCV's BMP reader types
    every such file grey under UNCHANGED, turning a 24-bit colour image grey.
    """
    if fmt == "bmp" and _bmp_header_bytes(data) == _BMP_CORE_HEADER_BYTES:
        return cv2.IMREAD_COLOR
    return cv2.IMREAD_UNCHANGED


def _tiff_size(data: bytes) -> tuple[int, int] | None:
    endian = "<" if data[:2] == b"II" else ">"
    if len(data) < 8:
        return None
    (ifd,) = struct.unpack(endian + "I", data[4:8])
    if ifd + 2 > len(data):
        return None
    (count,) = struct.unpack(endian + "H", data[ifd:ifd + 2])
    w = h = None
    for k in range(min(count, 512)):
        off = ifd + 2 + 12 * k
        if off + 12 > len(data):
            break
        tag, typ = struct.unpack(endian + "HH", data[off:off + 4])
        if tag in (256, 257):
            value = (struct.unpack(endian + "H", data[off + 8:off + 10])[0] if typ == 3
                     else struct.unpack(endian + "I", data[off + 8:off + 12])[0])
            if tag == 256:
                w = int(value)
            else:
                h = int(value)
    return (w, h) if w is not None and h is not None else None


def header_size(data: bytes, fmt: str) -> tuple[int, int] | None:
    """(width, height) from the header, or None when the header does not say."""
    parser = {"png": _png_size, "jpeg": _jpeg_size, "tiff": _tiff_size, "bmp": _bmp_size}[fmt]
    try:
        return parser(data)
    except struct.error:
        return None


# The plugin classes rather than PIL.Image.open: open() refuses (or warns
# about) sizes beyond Pillow's own global pixel limit before telling the
# size, and the limit that matters here is the caller's max_pixels.
_PILLOW_READERS: dict[str, type[ImageFile.ImageFile]] = {
    "png": PngImagePlugin.PngImageFile,
    "jpeg": JpegImagePlugin.JpegImageFile,
    "tiff": TiffImagePlugin.TiffImageFile,
    "bmp": BmpImagePlugin.BmpImageFile,
}


#: How much of a PNG, JPEG or BMP file Pillow is shown. Their headers come
#: first, but Pillow walks PNG chunks and JPEG segments in Python: a crafted
#: 32 MB file of tiny ones kept it busy 15-18 s. A TIFF is shown whole (its
#: directory may lie anywhere; Pillow reads one directory and its values
#: lazily: 0.1 s for 30 MB).
PILLOW_HEADER_BYTES = 1 << 20


def pillow_header_size(data: bytes, fmt: str) -> tuple[int, int] | None:
    """(width, height) as Pillow reads it from the header, or None when it cannot.

    Pillow reads only the header here (the pixels are decoded lazily, and
    never asked for).
    """
    shown = data if fmt == "tiff" else data[:PILLOW_HEADER_BYTES]
    try:
        with _PILLOW_READERS[fmt](io.BytesIO(shown)) as im:
            w, h = im.size
    # Pillow's header readers fail in many ways (SyntaxError, OSError,
    # ValueError, EOFError, struct.error, ...); to us each means the same:
    # Pillow cannot tell the size.
    except Exception:
        return None
    return int(w), int(h)


def _refuse_unless_size_allowed(data: bytes, fmt: str, field: str, max_pixels: int) -> None:
    """Refuse the image from its header alone: no size given, empty, or too many pixels.

    Raises
    ------
    InvalidImageError
        The header does not give the size (decoding would be the only way
        to learn it), gives an empty size, or more than ``max_pixels``.
    """
    size = header_size(data, fmt) or pillow_header_size(data, fmt)
    if size is None:
        raise InvalidImageError(f"the {fmt} header does not give the image size", field)
    w, h = size
    if w <= 0 or h <= 0:
        raise InvalidImageError(f"the {fmt} header gives an empty size {w}x{h}", field)
    if w * h > max_pixels:
        raise InvalidImageError(
            f"image has {w}x{h} = {w * h} pixels, more than the limit {max_pixels}", field
        )


def decode_image(
    data: bytes, field: str, max_pixels: int, allow_alpha_drop: bool = True
) -> NDArray[Any]:
    """Decode an uploaded image to (H, W) grey or (H, W, 3) RGB, uint8 or uint16.

    Parameters
    ----------
    data : bytes
        The file as uploaded.
    field : str
        Form field name, reported in errors.
    max_pixels : int
        Largest accepted width * height.
    allow_alpha_drop : bool
        Drop an alpha channel (True) rather than refusing the image.

    Raises
    ------
    InvalidImageError
        Not one of the accepted formats, a header that does not give the
        size, undecodable, too many pixels, or an unsupported sample type
        (e.g. 32-bit float TIFF).
    """
    if not data:
        raise InvalidImageError("the image file is empty", field)
    fmt = sniff_format(data)
    if fmt is None:
        raise InvalidImageError("not a PNG, JPEG, TIFF or BMP image", field)
    _refuse_unless_size_allowed(data, fmt, field, max_pixels)
    buf = np.frombuffer(data, dtype=np.uint8)
    try:
        img = cv2.imdecode(buf, _imread_flags(data, fmt))
    except cv2.error as exc:
        raise InvalidImageError(f"the {fmt} data cannot be decoded: {exc}", field) from exc
    if img is None or img.size == 0:
        raise InvalidImageError(f"the {fmt} data cannot be decoded", field)
    if img.shape[0] * img.shape[1] > max_pixels:
        raise InvalidImageError(
            f"image has {img.shape[1]}x{img.shape[0]} pixels, more than the limit {max_pixels}",
            field,
        )
    if img.dtype not in (np.uint8, np.uint16):
        raise InvalidImageError(
            f"samples of type {img.dtype} are not supported (8 or 16 bit only)", field
        )
    if img.ndim == 3:
        channels = img.shape[2]
        if channels == 1:
            img = img[:, :, 0]
        elif channels == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
        elif channels == 4 and allow_alpha_drop:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
        else:
            raise InvalidImageError(f"{channels} colour channels are not supported", field)
    return np.ascontiguousarray(img)


def encode_png(image: NDArray[np.uint8]) -> bytes:
    """PNG bytes of an (H, W) grey or (H, W, 3) RGB uint8 image."""
    bgr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else image
    ok, buf = cv2.imencode(".png", bgr)
    if not ok:
        raise InvalidImageError("could not encode the overlay as PNG", "overlay")
    return bytes(buf.tobytes())
