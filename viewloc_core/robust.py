"""Robust statistics shared by the fits: a fast median and Tukey's biweight."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]

#: Tukey's biweight constant, in robust standard deviations (95% efficiency
#: for Gaussian residuals).
TUKEY_C = 4.685


def median(values: Array) -> float:
    """Median of a 1D array (np.median's value, without its overhead)."""
    n = len(values)
    half = n // 2
    if n % 2:
        return float(np.partition(values, half)[half])
    part = np.partition(values, (half - 1, half))
    return 0.5 * float(part[half - 1] + part[half])


def tukey_weights(r: Array, min_scale: float) -> tuple[Array, float]:
    """Tukey biweights of residuals, with their robust scale.

    Parameters
    ----------
    r : (N,) float64
        Residuals.
    min_scale : float
        Floor of the scale (1.4826 x the median absolute deviation), in the
        residuals' unit: a fit that is exact for most residuals must not
        reject the rest for being a hair off.

    Returns
    -------
    weights : (N,) float64 in [0, 1]
    scale : float
    """
    mad = median(np.abs(r - median(r)))
    scale = max(1.4826 * mad, min_scale)
    u = r * (1.0 / (TUKEY_C * scale))
    w = 1.0 - u * u
    np.maximum(w, 0.0, out=w)
    w *= w
    return w, scale
