"""The attribute density of clutter features, estimated from the image itself.

Pope & Lowe weigh a pairing of an image feature with a model feature by how
much likelier its attributes are under the model than under clutter. A fixed
clutter density (:func:`viewloc_core.align._log_background_density`) does not
know the image: on a checkerboard or a tiled floor, hundreds of right-angle
junctions repeat one attribute value, each pairs with every right-angle
junction of the model, and a budget of pairings is spent on them before the
part's own features get a share. The image's own features tell how common an
attribute value is here: a kernel density over them, each feature left out of
its own estimate, mixed with the fixed prior as a few pseudo-features so that
an image with a handful of features (mostly the part's own) keeps the prior.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter, gaussian_filter1d

F64 = NDArray[np.float64]

#: Weight of the fixed prior, in features: with fewer image features of a
#: kind than this, the prior dominates the estimate. Hard bench set (busy
#: images only, 640x480): 34-35 of 80 missed for 5 to 80 pseudo-features,
#: 38 with the prior alone.
PRIOR_PSEUDO_FEATURES = 20.0

#: Histogram bin of the kernel density, in attribute standard deviations; the
#: kernel is one standard deviation wide (two bins).
_BIN = 0.5
_KERNEL_BINS = 1.0 / _BIN
#: The kernel is cut at this many standard deviations.
_TRUNCATE = 4.0
_REACH_BINS = int(_TRUNCATE / _BIN)
#: Weight the discrete smoothing kernel gives a count's own bin, per axis
#: (close to the continuous peak 1/sqrt(2π) per standard deviation).
_OWN_WEIGHT = float(gaussian_filter1d(np.eye(1, 2 * _REACH_BINS + 1, _REACH_BINS)[0],
                                      _KERNEL_BINS, mode="constant",
                                      truncate=_TRUNCATE)[_REACH_BINS])


def log_image_density(attrs: F64, sd: F64, log_prior: F64) -> F64:
    """Log clutter density at each feature's attributes, from the other features.

    Parameters
    ----------
    attrs : (N, D) float64
        Attributes of one kind's image features (D >= 1, those in use).
    sd : (D,) float64
        Pairing standard deviation of each attribute: the kernel's width.
    log_prior : (N,) float64
        Log of the fixed clutter density at each feature's attributes.

    Returns
    -------
    (N,) float64
        Log of the mixture ``((N - 1) * kde_loo + n0 * prior) / (N - 1 + n0)``,
        the same unit as ``log_prior``: ``kde_loo`` is the Gaussian kernel
        density of the other N - 1 features, ``n0`` is
        :data:`PRIOR_PSEUDO_FEATURES`.
    """
    log_prior = np.asarray(log_prior, np.float64)
    out = log_prior.copy()
    # A feature with an undefined attribute keeps the prior and is no one's
    # neighbour.
    finite = np.isfinite(attrs).all(axis=1) & np.isfinite(log_prior)
    z = attrs[finite] / sd
    n, d = z.shape
    if n < 2:
        return out
    # A smoothed histogram costs O(N) where pairwise kernels would cost
    # O(N^2): a checkerboard's thousands of junctions sit in a few bins.
    lo = z.min(axis=0) - _TRUNCATE  # the kernel reaches 4 sd: room on both sides
    cell = np.floor((z - lo) / _BIN).astype(np.int64)
    counts = np.zeros(tuple(cell.max(axis=0) + 1 + _REACH_BINS), np.float64)
    np.add.at(counts, tuple(cell.T), 1.0)
    smooth = gaussian_filter(counts, _KERNEL_BINS, mode="constant", truncate=_TRUNCATE)
    # Leave one out: a feature's own count adds the kernel's centre weight to
    # its bin. Then counts per bin -> count density per unit of z.
    others = np.maximum(smooth[tuple(cell.T)] - _OWN_WEIGHT**d, 0.0) / _BIN**d
    # Per unit of z -> per unit of the attributes themselves.
    log_others = np.log(np.maximum(others, 1e-300)) - float(np.sum(np.log(sd)))
    out[finite] = (np.logaddexp(log_others, np.log(PRIOR_PSEUDO_FEATURES) + log_prior[finite])
                   - np.log(n - 1 + PRIOR_PSEUDO_FEATURES))
    return out
