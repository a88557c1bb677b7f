"""Near-symmetries: half turns that map a part almost onto itself.

A part that is nearly an ellipsoid, a box or a cylinder (an egg with a few
bumps, a casting with one boss) has almost the same outline after a half
turn about any of its principal axes, from every viewpoint. A contour fit
cannot tell such a pose from the true one (hard bench set, free-form part:
6 of 16 poses that came out wrong were within 30° of a half turn of the
truth about a principal axis). Unlike exact symmetries these poses are
wrong, and the small differences (a bump, a dent) show in the shading:
:func:`viewloc_core.localize` tries them as extra starts and lets contour
and shading decide.

Found on the part's surface samples (:mod:`viewloc_core.shading`): the
principal axes of the sample cloud; a half turn about one through the
centroid is a near-symmetry when it moves the samples by little on average
onto the surface (nearest-sample distance, relative to the part's size) and
is not one of the part's exact symmetries (those are equivalent poses, not
rivals).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from viewloc_core.pose import Pose
from viewloc_core.shading import SurfaceSamples
from viewloc_core.symmetry import Symmetries, within_angle_deg

F64 = NDArray[np.float64]

#: A half turn is a near-symmetry when the turned samples lie on average
#: within this share of the part's extent of the surface, beyond half the
#: sampling spacing (bench parts: the free-form egg 1.1-1.4 % for its three
#: axes, the L-bracket 6.6-13 %).
MAX_MEAN_GAP_SHARE = 0.03

#: A half turn within this angle of an exact symmetry is that symmetry.
EXACT_TOL_DEG = 10.0


@dataclass(frozen=True, slots=True, eq=False)
class NearSymmetries:
    """Half turns that map a part almost onto itself.

    Attributes
    ----------
    rotations : (K, 3, 3) float64
        Rotations in the part's frame (K may be 0).
    centre_mm : (3,) float64
        The point they turn about (the samples' centroid), part frame, mm.
    mean_gap_mm : (K,) float64
        Mean distance of the turned samples from the surface, mm.
    """

    rotations: F64
    centre_mm: F64
    mean_gap_mm: F64

    def twins(self, pose: Pose) -> list[Pose]:
        """The poses that show the part turned by each near-symmetry.

        A point ``X`` of the part goes to ``S (X - c) + c`` before ``pose``
        applies: rotation ``R S``, translation ``t + R (c - S c)``.

        Parameters
        ----------
        pose : Pose
            Part frame -> camera.

        Returns
        -------
        list of Pose
            One per rotation, in order.
        """
        c = self.centre_mm
        R, t = pose.R_m2c, pose.t_m2c
        return [Pose(R @ S, t + R @ (c - S @ c)) for S in self.rotations]


def near_symmetries(samples: SurfaceSamples, exact: Symmetries) -> NearSymmetries:
    """The half turns about the principal axes that nearly map the part onto itself.

    Parameters
    ----------
    samples : SurfaceSamples
        Even samples of the part's surface, part frame, mm.
    exact : Symmetries
        The part's exact symmetry group (excluded).

    Returns
    -------
    NearSymmetries
    """
    pts = np.asarray(samples.points_mm, dtype=np.float64)
    centre = pts.mean(axis=0)
    rel = pts - centre
    _, axes = np.linalg.eigh(rel.T @ rel)
    tree = cKDTree(pts)
    rotations, gaps = [], []
    identity = np.eye(3)
    for axis in axes.T:
        S = 2.0 * np.outer(axis, axis) - identity  # half turn about ``axis``
        if within_angle_deg(identity, S, exact, EXACT_TOL_DEG):
            continue
        dist, _ = tree.query(rel @ S.T + centre)
        gap = float(dist.mean())
        # Nearest-sample distances of points on the surface itself are about
        # half the sample spacing: that much is not a difference of shape.
        if gap - 0.5 * samples.spacing_mm < MAX_MEAN_GAP_SHARE * samples.extent_mm:
            rotations.append(S)
            gaps.append(gap)
    return NearSymmetries(np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3), centre,
                          np.asarray(gaps, dtype=np.float64))
