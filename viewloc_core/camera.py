"""Pinhole camera intrinsics in the OpenCV convention.

Pixel coordinates follow OpenCV: the centre of the top-left pixel is (0, 0),
x to the right, y down; the camera looks along +z.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from viewloc_core.errors import InvalidCameraError

#: Focal lengths (pixels) as multiples of the image's longer side: below
#: the first the camera would see more than about 170° across, which no
#: pinhole model describes; above the second less than 0.06°. Outside them
#: the pose arithmetic loses its precision (a focal length of 1e-10 px made
#: the pose's rotation NaN).
FOCAL_SIDES = (0.05, 1000.0)
#: How far the principal point may lie outside the image, in image sizes
#: (a crop of a larger sensor keeps the sensor's principal point).
PRINCIPAL_POINT_MARGIN_SIDES = 10.0
#: The largest magnitude of a distortion coefficient: calibrated lenses
#: have |k| up to tens (rational models), |p| below 1; p1 = 1e10 made the
#: pose's Jacobian singular.
MAX_DISTORTION_COEFFICIENT = 1e4
#: The lens model must take every pixel of the image back to one viewing
#: ray: solved for the ray and distorted again, a pixel must come back
#: within this many pixels, where the model keeps the image's orientation
#: (no fold). Coefficients within MAX_DISTORTION_COEFFICIENT can still
#: fold the image or leave its corners with no ray at all (a denominator
#: of the rational model reaching 0: a projected pose became NaN and the
#: request a server error). The calibrations tried pass with room to spare
#: (OpenCV's sample calibration, a 110° wide-angle lens, an action camera's
#: rational model, a crop's principal point outside the image: through
#: Camera.ray and back within a thousandth of a pixel).
DISTORTION_ROUND_TRIP_PX = 0.5
#: Iterations (at most) and the step at which OpenCV's undistortion stops.
#: Its default stops after a few: through the corner pixel of a lens seeing
#: 110° across (f = 300 px at 640x480, k1 = -0.28, k2 = 0.07) the ray was
#: 38 px off, after 20 iterations 4e-8 px.
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
#: Pixels along each side of the image, and every second of them across
#: it, at which the lens model is checked.
_DISTORTION_CHECK_STEPS = 16


@dataclass(frozen=True, slots=True)
class Camera:
    """Intrinsics and image size of a (possibly distorted) pinhole camera.

    Attributes
    ----------
    fx, fy : float
        Focal lengths in pixels.
    cx, cy : float
        Principal point in pixels (OpenCV convention).
    width, height : int
        Image size in pixels.
    dist : tuple of float
        OpenCV distortion coefficients ``(k1, k2, p1, p2[, k3])``; empty for
        an ideal pinhole.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    dist: tuple[float, ...] = field(default=())

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            if not math.isfinite(value):
                raise InvalidCameraError(f"{name} must be finite, got {value}", name)
        if self.fx <= 0 or self.fy <= 0:
            raise InvalidCameraError("focal lengths fx and fy must be positive", "fx")
        if self.width <= 0 or self.height <= 0:
            raise InvalidCameraError("width and height must be positive", "width")
        side = max(self.width, self.height)
        low, high = FOCAL_SIDES[0] * side, FOCAL_SIDES[1] * side
        for name in ("fx", "fy"):
            if not low <= getattr(self, name) <= high:
                raise InvalidCameraError(
                    f"{name} must be between {low:g} and {high:g} pixels for a "
                    f"{self.width}x{self.height} image, got {getattr(self, name):g}", name)
        for name, size in (("cx", self.width), ("cy", self.height)):
            margin = PRINCIPAL_POINT_MARGIN_SIDES * size
            if not -margin <= getattr(self, name) <= size + margin:
                raise InvalidCameraError(
                    f"{name} must lie within {PRINCIPAL_POINT_MARGIN_SIDES:g} image sizes of "
                    f"the image, got {getattr(self, name):g}", name)
        if len(self.dist) not in (0, 4, 5, 8):
            raise InvalidCameraError("dist must have 4, 5 or 8 coefficients", "dist")
        if not all(math.isfinite(c) for c in self.dist):
            raise InvalidCameraError("dist coefficients must be finite", "dist")
        if any(abs(c) > MAX_DISTORTION_COEFFICIENT for c in self.dist):
            raise InvalidCameraError(
                f"dist coefficients must be at most {MAX_DISTORTION_COEFFICIENT:g} in "
                "magnitude", "dist")
        if self.has_distortion:
            problem = _distortion_problem(self.fx, self.fy, self.cx, self.cy, self.width,
                                          self.height, tuple(float(c) for c in self.dist))
            if problem is not None:
                raise InvalidCameraError(problem, "dist")

    @property
    def K(self) -> NDArray[np.float64]:
        """(3, 3) float64 intrinsic matrix."""
        return np.array(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]],
            dtype=np.float64,
        )

    @property
    def has_distortion(self) -> bool:
        """True when any distortion coefficient is non-zero."""
        return any(c != 0.0 for c in self.dist)

    @property
    def dist8(self) -> NDArray[np.float64]:
        """The distortion coefficients zero-padded to OpenCV's 8, (8,) float64
        (the form the compiled kernels take)."""
        padded = np.zeros(8)
        padded[:len(self.dist)] = self.dist
        return padded

    @property
    def focal_px(self) -> float:
        """Geometric mean focal length in pixels, the scale used for distances."""
        return math.sqrt(self.fx * self.fy)

    @classmethod
    def from_K(
        cls,
        K: NDArray[np.floating],
        width: int,
        height: int,
        dist: tuple[float, ...] = (),
    ) -> Camera:
        """Build from a (3, 3) intrinsic matrix (skew must be zero)."""
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):
            raise InvalidCameraError(f"K must be 3x3, got shape {K.shape}", "K")
        return cls(
            float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
            int(width), int(height), tuple(float(c) for c in dist),
        )

    def scaled(self, factor: float) -> Camera:
        """The same camera for an image resized by ``factor`` (pyramid levels).

        Pixel centres map as ``u' = (u + 0.5) * factor - 0.5``.
        """
        return Camera(
            self.fx * factor,
            self.fy * factor,
            (self.cx + 0.5) * factor - 0.5,
            (self.cy + 0.5) * factor - 0.5,
            max(1, round(self.width * factor)),
            max(1, round(self.height * factor)),
            self.dist,
        )

    def project(self, pts_cam: NDArray[np.floating]) -> NDArray[np.float64]:
        """Project camera-frame points to pixels.

        Parameters
        ----------
        pts_cam : (N, 3) array
            Points in the camera frame, mm, z > 0.

        Returns
        -------
        (N, 2) float64
            Pixel coordinates (with distortion applied when present).
        """
        pts = np.asarray(pts_cam, dtype=np.float64).reshape(-1, 3)
        uv = np.empty((len(pts), 2))
        u, v = uv[:, 0], uv[:, 1]
        np.divide(pts[:, 0], pts[:, 2], out=u)
        np.divide(pts[:, 1], pts[:, 2], out=v)
        if self.has_distortion:
            u[:], v[:] = _distort(u, v, self.dist)
        # Column by column, in place: this runs in every refinement step, and
        # is twice as fast as dividing (N, 2) by a broadcast (N, 1).
        u *= self.fx
        u += self.cx
        v *= self.fy
        v += self.cy
        return uv

    def undistort_points(self, uv: NDArray[np.floating]) -> NDArray[np.float64]:
        """Remove lens distortion from pixel positions (identity without it).

        Parameters
        ----------
        uv : (N, 2) array
            Distorted pixel coordinates.

        Returns
        -------
        (N, 2) float64
            Pixel coordinates an ideal pinhole with the same K would see.
        """
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        if not self.has_distortion:
            return uv.copy()
        und = cv2.undistortPoints(
            uv.reshape(-1, 1, 2), self.K, np.asarray(self.dist, dtype=np.float64), P=self.K,
            criteria=_UNDISTORT_CRITERIA,
        )
        return und.reshape(-1, 2).astype(np.float64)

    def ray(self, uv: NDArray[np.floating]) -> NDArray[np.float64]:
        """Unit viewing rays (camera frame) through pixels, distortion removed.

        Parameters
        ----------
        uv : (N, 2) array
            Pixel coordinates.

        Returns
        -------
        (N, 3) float64
            Unit vectors with positive z.
        """
        und = self.undistort_points(uv)
        rays = np.stack(
            [(und[:, 0] - self.cx) / self.fx, (und[:, 1] - self.cy) / self.fy,
             np.ones(len(und))],
            axis=1,
        )
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def _distort(
    xn: NDArray[np.float64], yn: NDArray[np.float64], dist: tuple[float, ...]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Brown-Conrady distortion of normalised coordinates (OpenCV's model)."""
    c = list(dist) + [0.0] * (8 - len(dist))
    k1, k2, p1, p2, k3, k4, k5, k6 = c
    r2 = xn * xn + yn * yn
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
    yd = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
    return xd, yd


def _check_pixels(width: int, height: int) -> NDArray[np.float64]:
    """(N, 2) pixels at which a lens model is checked: along the image's
    border, where distortion is strongest, and on a grid across it."""
    steps = np.linspace(0.0, 1.0, _DISTORTION_CHECK_STEPS + 1)
    xs, ys = (width - 1) * steps, (height - 1) * steps
    border = np.concatenate([
        np.stack([xs, np.zeros_like(xs)], axis=1),
        np.stack([xs, np.full_like(xs, height - 1)], axis=1),
        np.stack([np.zeros_like(ys), ys], axis=1),
        np.stack([np.full_like(ys, width - 1), ys], axis=1),
    ])
    grid = np.stack(np.meshgrid(xs[::2], ys[::2]), axis=-1).reshape(-1, 2)
    return np.concatenate([border, grid])


def _distortion_jacobian(
    xn: NDArray[np.float64], yn: NDArray[np.float64], dist: tuple[float, ...],
) -> tuple[NDArray[np.float64], ...]:
    """The distorted coordinates of normalised points and the distortion's
    (2, 2) Jacobian there, by forward differences: ``xd, yd, j11, j12, j21,
    j22``, each (N,)."""
    step = 1e-7
    xd, yd = _distort(xn, yn, dist)
    ax, ay = _distort(xn + step, yn, dist)
    bx, by = _distort(xn, yn + step, dist)
    return xd, yd, (ax - xd) / step, (bx - xd) / step, (ay - yd) / step, (by - yd) / step


@functools.lru_cache(maxsize=256)
def _distortion_problem(fx: float, fy: float, cx: float, cy: float, width: int, height: int,
                        dist: tuple[float, ...]) -> str | None:
    """Why the lens model does not take the image's pixels one to one back
    to viewing rays (see DISTORTION_ROUND_TRIP_PX), or None when it does.

    Each checked pixel is taken back to its ray as
    :meth:`Camera.undistort_points` takes it and distorted again: what is
    checked is what the engine will compute. Cached: a service sees the
    same few cameras over and over, and the check costs a millisecond or
    more.
    """
    pixels = _check_pixels(width, height)
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    with np.errstate(all="ignore"):
        rays = np.asarray(cv2.undistortPoints(
            pixels.reshape(-1, 1, 2), K, np.asarray(dist, np.float64),
            criteria=_UNDISTORT_CRITERIA), np.float64).reshape(-1, 2)
        xd, yd, j11, j12, j21, j22 = _distortion_jacobian(rays[:, 0], rays[:, 1], dist)
        miss_px = np.hypot(fx * xd + cx - pixels[:, 0], fy * yd + cy - pixels[:, 1])
        det = j11 * j22 - j12 * j21
    worst = int(np.argmax(np.where(np.isfinite(miss_px), miss_px, np.inf)))
    if not miss_px[worst] <= DISTORTION_ROUND_TRIP_PX:
        u, v = pixels[worst]
        return (f"the distortion coefficients leave pixel ({u:.0f}, {v:.0f}) of the "
                f"{width}x{height} image without a viewing ray (the lens model does not "
                "reach it)")
    folded = np.flatnonzero(~(det > 0.0))
    if len(folded):
        u, v = pixels[folded[0]]
        return (f"the distortion coefficients fold the {width}x{height} image over at "
                f"pixel ({u:.0f}, {v:.0f}) (two viewing rays would meet there)")
    return None


def undistort(
    image: NDArray[Any], camera: Camera, nearest: bool = False
) -> tuple[NDArray[Any], Camera]:
    """The image as a distortion-free camera with the same K would have taken it.

    Used for the training photos of ``from-images`` (the task removes the
    distortion first and hands the engine the same K without coefficients)
    and for their masks where the visual hull is carved through the pinhole
    alone (:mod:`viewloc_core.visual_hull`). Localization needs no such step:
    the engine takes ``dist`` into account in its rays and its refinement, so
    scenes go to it as taken.

    Parameters
    ----------
    image : (H, W) or (H, W, C) uint8 or uint16
        Pixels as taken by ``camera``.
    camera : Camera
        Its intrinsics, with or without distortion.
    nearest : bool
        Nearest-neighbour resampling (for masks and labels).

    Returns
    -------
    image : same shape and dtype
        Unchanged (the same array) when the camera has no distortion.
    camera : Camera
        ``camera`` without distortion coefficients.
    """
    if not camera.has_distortion:
        return image, camera
    h, w = image.shape[:2]
    K = camera.K
    map_x, map_y = cv2.initUndistortRectifyMap(
        K, np.asarray(camera.dist, np.float64), None, K, (w, h), cv2.CV_32FC1
    )
    flags = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    out = cv2.remap(image, map_x, map_y, flags, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return out, Camera(camera.fx, camera.fy, camera.cx, camera.cy, w, h)
