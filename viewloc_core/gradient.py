"""Image gradient shared by the feature extractor and the pose refinement.

Colour images: per pixel the gradient of the channel where it is largest (as
LINE-MOD does), so an edge between two colours of equal brightness, which any
grey conversion loses, stays visible.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

from viewloc_core.feature_kernels import strongest_channel

F32 = NDArray[np.float32]


def _sobel(img: F32) -> tuple[F32, F32]:
    # Sobel divided by 8: the unit is intensity per pixel.
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    return np.asarray(gx, dtype=np.float32), np.asarray(gy, dtype=np.float32)


def image_gradient(img: F32) -> tuple[F32, F32]:
    """(∂I/∂x, ∂I/∂y) of a grey or colour float32 image.

    Parameters
    ----------
    img : (H, W) or (H, W, C) float32
        Intensities (any unit).

    Returns
    -------
    gx, gy : (H, W) float32
        Intensity units per pixel; for colour, per pixel those of the channel
        with the largest gradient magnitude (the first one on ties).
    """
    if img.ndim == 2 or img.shape[2] == 1:
        return _sobel(img.reshape(img.shape[:2]))
    # One Sobel pass over all channels, and the per-pixel choice in one
    # compiled loop: per-channel planes, OpenCV's multiply/add/compare and
    # numpy's argmax over a trailing axis of 3 all cost several times more.
    gx_channels, gy_channels = _sobel(img)
    return strongest_channel(gx_channels, gy_channels)
