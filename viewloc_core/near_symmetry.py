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

Found by :func:`viewloc_core.symmetry.near_half_turns` with the surface test
of the exact symmetry detection: a half turn about a principal axis through
the surface centroid is a near-symmetry when it moves the surface by little
on average (relative to the part's size), and is not one of the part's exact
symmetries (those are equivalent poses, not rivals).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from numpy.typing import NDArray

from viewloc_core.pose import Pose
from viewloc_core.symmetry import Symmetries, near_half_turns

F64 = NDArray[np.float64]

#: A half turn is a near-symmetry when the turned surface lies on average
#: within this share of the part's bounding-box diagonal of the surface,
#: beyond the sampling floor (bench parts: the free-form egg 1.0-1.2 % for
#: its three axes, the L-bracket 5.4-10 %).
MAX_MEAN_GAP_SHARE = 0.03


@dataclass(frozen=True, slots=True, eq=False)
class NearSymmetries:
    """Half turns that map a part almost onto itself.

    Attributes
    ----------
    transforms : (K, 4, 4) float64
        Rigid transforms of the part's frame (K may be 0).
    mean_gap_mm : (K,) float64
        Mean distance of the turned surface from the surface, beyond the
        sampling floor, mm.
    """

    transforms: F64
    mean_gap_mm: F64

    def twins(self, pose: Pose) -> list[Pose]:
        """The poses that show the part moved by each near-symmetry.

        A point ``X`` of the part goes to ``T X`` before ``pose`` applies:
        rotation ``R T_R``, translation ``t + R T_t``.

        Parameters
        ----------
        pose : Pose
            Part frame -> camera.

        Returns
        -------
        list of Pose
            One per transform, in order.
        """
        R, t = pose.R_m2c, pose.t_m2c
        return [Pose(R @ T[:3, :3], t + R @ T[:3, 3]) for T in self.transforms]


def near_symmetries(mesh: trimesh.Trimesh, exact: Symmetries) -> NearSymmetries:
    """The half turns about the principal axes that nearly map the part onto itself.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The part, mm, in the frame poses refer to.
    exact : Symmetries
        The part's exact symmetry group (excluded).

    Returns
    -------
    NearSymmetries
    """
    transforms, gaps = near_half_turns(mesh, exact, max_gap_frac=MAX_MEAN_GAP_SHARE)
    return NearSymmetries(transforms, gaps)
