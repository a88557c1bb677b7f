"""Result values of localization: 2D similarity, 6D pose, quality."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from viewloc_core.pose import Pose


@dataclass(frozen=True, slots=True)
class Similarity2D:
    """2D similarity that maps a model view into the image (paper §4.2: r = (x, y, α, s)).

    A model-view point ``p`` (pixels of the training image, relative to the
    projection of the object origin) lands at
    ``[x, y] + scale * Rot(angle) @ p`` in the image, where
    ``Rot(a) = [[cos a, -sin a], [sin a, cos a]]`` acts on OpenCV pixel
    coordinates (y down, so a positive angle turns clockwise on screen).
    ``(x, y)`` is therefore where the object origin appears in the image.

    Attributes
    ----------
    x, y : float
        Image position of the object origin, pixels.
    angle_deg : float
        In-plane rotation α, degrees, in (-180, 180].
    scale : float
        Image scale s relative to the training view (> 0).
    """

    x: float
    y: float
    angle_deg: float
    scale: float

    @property
    def matrix(self) -> NDArray[np.float64]:
        """(2, 3) affine matrix model-view pixels -> image pixels."""
        a = np.radians(self.angle_deg)
        c, s = self.scale * np.cos(a), self.scale * np.sin(a)
        return np.array([[c, -s, self.x], [s, c, self.y]])

    def apply(self, pts: NDArray[np.floating]) -> NDArray[np.float64]:
        """Map (N, 2) model-view points to (N, 2) image points."""
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
        return pts @ self.matrix[:, :2].T + self.matrix[:, 2]


@dataclass(frozen=True, slots=True)
class Detection:
    """One localized instance of an object.

    Attributes
    ----------
    score : float
        Calibrated match quality in [0, 1]; higher is better. Refined: the
        share of the part's whole predicted contour confirmed by image
        edges, the part's own edges weighing half and the contour outside
        the image counting as unconfirmed (README, "What the score means").
    log_probability : float
        g(E, T) ≈ log P(H | E, T) of the probabilistic alignment (paper Eq. 1).
    model_view : int
        Index of the matched model view.
    azimuth_deg, polar_deg : float
        Viewing angles of the best-fitting training view of that model view.
    similarity : Similarity2D
        The 2D match (x, y, α, s).
    pose : Pose
        Object -> camera, mm.
    refined : bool
        Whether the pose was refined against image edges (§5.2).
    pose_std : (6,) float64 or None
        Standard deviations of the refined pose: rotation about camera x, y, z
        (deg), then translation x, y, z (mm). None when not estimated.
    object_id : str or None
        Which object, when several were searched at once.
    """

    score: float
    log_probability: float
    model_view: int
    azimuth_deg: float
    polar_deg: float
    similarity: Similarity2D
    pose: Pose
    refined: bool = False
    pose_std: NDArray[np.float64] | None = field(default=None)
    object_id: str | None = None
