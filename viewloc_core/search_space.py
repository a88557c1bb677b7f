"""Where a station knows the part can be: an image region and a depth range.

A QA station's camera is fixed: the part lies on a fixture or a conveyor at
a known working distance, in a known part of the image. Said in the request
(API ``options.roi`` and ``options.depth_mm``, HALCON's search domain and
distance range), the search leaves out what cannot be the part: clutter
elsewhere in the image no longer competes, and sizes the depth rules out
are not tried.

- :class:`ImageRegion` keeps the hypotheses whose centre lies in it
  (:meth:`ImageRegion.contains`).
- :class:`DepthRange` bounds the alignment's scales
  (:meth:`DepthRange.scale_bounds`) and drops fits outside it
  (:meth:`DepthRange.holds`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from viewloc_core.camera import Camera
from viewloc_core.detection import Detection
from viewloc_core.errors import InvalidInputError

#: How far the 2D scale the alignment and view search find may stray from
#: the one the true depth gives (their scale grids step about 7 %, and the
#: scale is the magnification at the depth of the matched view's features,
#: not of the origin): the scale bounds are widened by this factor each way.
SCALE_MARGIN = 1.25


def within_bounds(uv: NDArray[np.floating], bounds: NDArray[np.floating]) -> NDArray[np.bool_]:
    """(N,) bool: which of the (N, 2) points lie in the rectangle
    ``bounds`` = ``x0, y0, x1, y1`` (edges included)."""
    x0, y0, x1, y1 = np.asarray(bounds, np.float64)
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    return np.asarray((uv[:, 0] >= x0) & (uv[:, 0] <= x1) & (uv[:, 1] >= y0) & (uv[:, 1] <= y1))


@dataclass(frozen=True, slots=True)
class ImageRegion:
    """An axis-aligned rectangle of the image in which the part's centre lies.

    The part's centre is the image of its bounding-box centre (the point
    the search places hypotheses by). The whole image is still read: the
    clutter model, the colour statistics and the refinement's edges are
    those of the whole image, so a part inside the region is found as it is
    without one (a crop instead, LM-O every 4th photo and the hard set with
    a region around the part: AR_MSSD 0.174 -> 0.155 and 0.928 -> 0.860, as
    the part's own edges and colours took a larger share of the crop's
    statistics); only hypotheses outside it are not searched.

    Attributes
    ----------
    x, y : int
        Top-left pixel of the region, full-image pixels (OpenCV convention).
    width, height : int
        Size of the region, pixels (> 0).
    """

    x: int
    y: int
    width: int
    height: int

    def __post_init__(self) -> None:
        if self.x < 0 or self.y < 0:
            raise InvalidInputError("x and y must be >= 0", "options.roi")
        if self.width <= 0 or self.height <= 0:
            raise InvalidInputError("width and height must be positive", "options.roi")

    def check_within(self, width: int, height: int) -> None:
        """Raise InvalidInputError unless the region lies inside a
        ``width`` x ``height`` image."""
        if self.x + self.width > width or self.y + self.height > height:
            raise InvalidInputError(
                f"region x {self.x}..{self.x + self.width}, y {self.y}..{self.y + self.height}"
                f" reaches outside the {width}x{height} image", "options.roi")

    def bounds(self, factor: float = 1.0, margin_px: float = 0.0) -> NDArray[np.float64]:
        """(4,) float64 ``x0, y0, x1, y1``: the region's outer pixel edges on
        an image level ``factor`` times the full image's size, grown by
        ``margin_px`` level pixels on every side."""
        x0, y0 = self.x - 0.5, self.y - 0.5
        x1, y1 = x0 + self.width, y0 + self.height
        corners = (np.array([x0, y0, x1, y1]) + 0.5) * factor - 0.5
        return np.asarray(corners + np.array([-1.0, -1.0, 1.0, 1.0]) * margin_px, np.float64)

    def contains(self, uv: NDArray[np.floating], factor: float = 1.0,
                 margin_px: float = 0.0) -> NDArray[np.bool_]:
        """(N,) bool: which of the (N, 2) points (level pixels) lie in
        :meth:`bounds`."""
        return within_bounds(uv, self.bounds(factor, margin_px))


@dataclass(frozen=True, slots=True)
class DepthRange:
    """The depths the part's origin can have, camera z, mm.

    Attributes
    ----------
    min_mm, max_mm : float
        ``0 < min_mm < max_mm``: the depth (``t_mm[2]`` of the reported
        pose, the object frame's origin) of every detection.
    """

    min_mm: float
    max_mm: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.min_mm) and self.min_mm > 0):
            raise InvalidInputError("min must be positive", "options.depth_mm.min")
        if not (math.isfinite(self.max_mm) and self.max_mm > self.min_mm):
            raise InvalidInputError("max must be finite and greater than min",
                                    "options.depth_mm.max")

    def holds(self, detection: Detection) -> bool:
        """Whether the detection's origin lies in the range."""
        return self.min_mm <= float(detection.pose.t_m2c[2]) <= self.max_mm

    def scale_bounds(self, camera: Camera, factor: float, d0_mm: float, f_train_px: float,
                     diameter_mm: float, origin_offset_mm: float) -> tuple[float, float]:
        """The 2D scales (search level against the training views) at which
        a part whose origin lies in the range can appear.

        A training view shows the part's centre at ``d0_mm`` with focal
        length ``f_train_px``, and a 2D scale is the magnification at the
        depth of the matched view's features, up to half the diameter
        nearer or farther than the centre (``ref_depth_mm`` of
        :func:`~viewloc_core.pose_from_match.pose_from_similarity`): at
        distance d the search level shows the part ``camera.focal_px *
        factor * (d0 + r) / (f_train * (d + r))`` times as large, with
        ``|r| <= diameter / 2``. The centre lies
        ``origin_offset_mm`` from the origin whose depth the range bounds,
        and off the optical axis its distance along the ray is up to the
        widest ray's ``1 / cos`` more than its depth, while the image
        stretches what the ray sees by up to ``1 / cos**2``.
        :data:`SCALE_MARGIN` covers the searches' own scale error.

        Parameters
        ----------
        camera : Camera
            The (cropped) image's camera.
        factor : float
            Search-level pixels per image pixel.
        d0_mm, f_train_px : float
            The training camera's distance and focal length.
        diameter_mm : float
            The part's diameter.
        origin_offset_mm : float
            Distance of the part's bounding-box centre from its origin.

        Returns
        -------
        (float, float)
            Least and greatest scale; the least may exceed the greatest
            when no depth in the range fits a positive size.
        """
        corners = np.array([[0.0, 0.0], [camera.width, 0.0], [0.0, camera.height],
                            [camera.width, camera.height]]) - [camera.cx, camera.cy]
        widest = float(np.max(np.hypot(corners[:, 0] / camera.fx, corners[:, 1] / camera.fy)))
        ray_stretch = math.sqrt(1.0 + widest * widest)
        half = 0.5 * diameter_mm
        near = self.min_mm - origin_offset_mm - half
        far = (self.max_mm + origin_offset_mm + half) * ray_stretch
        unit = camera.focal_px * factor / f_train_px
        least = unit * max(d0_mm - half, 0.0) / far / SCALE_MARGIN
        greatest = (unit * (d0_mm + half) / near * ray_stretch**2 * SCALE_MARGIN if near > 0
                    else math.inf)
        return least, greatest
