"""The bytes the client uploads for an image given as a file, bytes or a pixel array.

A camera frame is already an array in memory. Sent uncompressed, it costs
the round trip almost nothing beyond its transfer: a 640x480 RGB frame as
BMP is encoded in about 2 ms and decoded by the service in under 1 ms,
where PNG (even at zlib level 1) takes about 20 ms to encode and 7 ms to
decode (measured through the bench's HTTP backend on the hard set). The
~0.9 MB crosses a gigabit link in about 7 ms, so uncompressed wins unless
the link is much slower than that.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeAlias

if TYPE_CHECKING:
    from numpy.typing import NDArray

#: What :func:`upload_file` accepts: file bytes, a path, or a pixel array.
ImageInput: TypeAlias = "bytes | str | Path | NDArray[Any]"


def upload_file(image: ImageInput, name: str, field: str = "image") -> tuple[str, bytes]:
    """(file name, file bytes) of one image for a multipart upload.

    Parameters
    ----------
    image : bytes, str, Path or numpy.ndarray
        File bytes (PNG, JPEG, TIFF or BMP) or a path to such a file, sent
        as they are; or pixels: (H, W) grey or (H, W, 3) RGB ``uint8`` (or
        an (H, W) ``bool`` mask, sent as 0 / 255), sent as an uncompressed
        BMP, or (H, W) grey ``uint16``, sent as an uncompressed TIFF.
    name : str
        File name for bytes (a path keeps its own; an array gets ``name``
        with the format's suffix).
    field : str
        The parameter's name, for the error message.

    Returns
    -------
    (str, bytes)
        File name and contents.

    Raises
    ------
    ValueError
        An array of another type or shape (16-bit colour, float, alpha):
        encode it yourself and pass the bytes.
    """
    if isinstance(image, (bytes, bytearray, memoryview, str, Path)):
        return file_bytes(image, name)
    if hasattr(image, "__array_interface__"):
        return _encoded_array(image, name, field)
    raise TypeError(f"{field}: expected bytes, a path or a numpy array, "
                    f"not {type(image).__name__}")


def file_bytes(data: bytes | bytearray | memoryview | str | Path,
               name: str) -> tuple[str, bytes]:
    """(file name, contents) of a file given as bytes (named ``name``) or a path."""
    if isinstance(data, (str, Path)):
        path = Path(data)
        return path.name, path.read_bytes()
    return name, bytes(data)


def _encoded_array(pixels: Any, name: str, field: str) -> tuple[str, bytes]:
    """BMP (8-bit) or TIFF (16-bit grey) bytes of an array, uncompressed."""
    import numpy as np
    from PIL import Image

    array = np.asarray(pixels)
    if array.dtype == np.bool_:
        array = array.astype(np.uint8) * 255  # a mask: non-zero is the object
    stem = name.rsplit(".", 1)[0]
    grey = array.ndim == 2
    rgb = array.ndim == 3 and array.shape[2] == 3
    if array.dtype == np.uint8 and (grey or rgb) and array.size:
        fmt, suffix = "BMP", "bmp"
    elif array.dtype == np.uint16 and grey and array.size:
        fmt, suffix = "TIFF", "tif"
    else:
        raise ValueError(
            f"{field}: an array must be (H, W) or (H, W, 3) uint8, or (H, W) uint16, "
            f"not {array.shape} {array.dtype}; encode other images yourself "
            "(PNG or TIFF bytes)")
    buf = io.BytesIO()
    # Pillow writes both without compression: the point is speed (module docstring).
    Image.fromarray(np.ascontiguousarray(array)).save(buf, format=fmt)
    return f"{stem}.{suffix}", buf.getvalue()
