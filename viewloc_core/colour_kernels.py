"""Per-pixel lookups by colour, compiled.

The part's colour cue reads each pixel's colour bin, or a value per bin,
at every pixel (:mod:`viewloc_core.part_colour`). In array form that is
three int32 copies of the image, two shifts and an or before the gather:
57-95 ms for a 5 MP frame on this machine. Here it is one pass over the
pixels, with the value looked up in a table indexed by the colour quantised
to 6 bits per channel: 23 ms for the bins of a 5 MP frame, 9 ms for its
posterior (the table's making included).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit
from numpy.typing import NDArray

#: Entries of a table indexed by a colour quantised to 6 bits per channel.
QUANTISED_COLOURS = 1 << 18

#: A table of histogram bins (int32) or of values per bin (float32).
ColourTable = NDArray[Any]


@njit(cache=True, nogil=True)
def lookup_by_colour(rgb: NDArray[np.uint8], table: ColourTable,
                     ) -> ColourTable:  # pragma: no cover - compiled
    """``table[(r >> 2) << 12 | (g >> 2) << 6 | (b >> 2)]`` of every pixel.

    Parameters
    ----------
    rgb : (H, W, 3) uint8, C-contiguous
        RGB colours.
    table : (QUANTISED_COLOURS,) int32 or float32
        A value per quantised colour: its histogram bin, or a value per bin
        already looked up.

    Returns
    -------
    (H, W), the table's dtype
    """
    height, width = rgb.shape[0], rgb.shape[1]
    out = np.empty((height, width), table.dtype)
    for y in range(height):
        for x in range(width):
            index = ((np.int64(rgb[y, x, 0]) >> 2) << 12 | (np.int64(rgb[y, x, 1]) >> 2) << 6
                     | (np.int64(rgb[y, x, 2]) >> 2))
            out[y, x] = table[index]
    return out


def warm_up() -> None:
    """Compile (or load from numba's cache) for the types the colour cue passes."""
    for dtype in (np.int32, np.float32):
        lookup_by_colour(np.zeros((1, 1, 3), np.uint8), np.zeros(QUANTISED_COLOURS, dtype))
