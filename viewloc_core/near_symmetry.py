"""Near-symmetries: half turns and reflections that map a part almost onto itself.

A part that is nearly an ellipsoid, a box or a cylinder (an egg with a few
bumps, a casting with one boss) has almost the same outline after a half
turn about any of its principal axes, from every viewpoint. A contour fit
cannot tell such a pose from the true one (hard bench set, free-form part:
6 of 16 poses that came out wrong were within 30° of a half turn of the
truth about a principal axis). Unlike exact symmetries these poses are
wrong, and the small differences (a bump, a dent) show in the shading:
:func:`viewloc_core.localize` tries them as extra starts and lets contour
and shading decide.

A part with a (near) mirror plane has a second kind of rival: the pose
*reversed in depth*. Reflecting the part in its mirror plane and then the
scene in the plane through the part's centre across the line of sight
gives a proper rotation (two reflections) whose outline is the same to
first order in the part's depth over its distance: a part tilted towards
the camera and the same part tilted away (the ambiguity of a plane's pose
under weak perspective; for an egg, the top seen from above and the
bottom seen from below). No half turn reaches it (hard bench set,
free-form part: 7 of the 15 poses that came out wrong were within 25° of
this reversal of the reported pose, 4-19° in most).

Found by :func:`viewloc_core.symmetry.near_half_turns` and
:func:`viewloc_core.symmetry.near_mirrors` with the surface test of the
exact symmetry detection: a half turn about a principal axis, or a
reflection through the surface centroid, is a near-symmetry when it moves
the surface by little on average (relative to the part's size); half turns
that are exact symmetries are left out (those are equivalent poses, not
rivals).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import trimesh
from numpy.typing import NDArray

from viewloc_core.pose import Pose, reorthonormalized
from viewloc_core.symmetry import (
    Symmetries,
    near_half_turns,
    near_mirrors,
    surface_centroid,
    surface_second_moment,
)

F64 = NDArray[np.float64]

#: A half turn is a near-symmetry when the turned surface lies on average
#: within this share of the part's bounding-box diagonal of the surface,
#: beyond the sampling floor (bench parts: the free-form egg 1.0-1.2 % for
#: its three axes, the L-bracket 5.4-10 %).
MAX_MEAN_GAP_SHARE = 0.03


@dataclass(frozen=True, slots=True, eq=False)
class NearSymmetries:
    """Half turns and reflections that map a part almost onto itself.

    Attributes
    ----------
    transforms : (K, 4, 4) float64
        Rigid transforms of the part's frame (K may be 0).
    mean_gap_mm : (K,) float64
        Mean distance of the turned surface from the surface, beyond the
        sampling floor, mm.
    mirrors : (M, 4, 4) float64
        Reflections of the part's frame (``det = -1``; M may be 0), each
        fixing ``centre``.
    mirror_gap_mm : (M,) float64
        The same distance for each reflection, mm.
    centre : (3,) float64
        The surface centroid, part frame, mm (where the depth reversal of
        :meth:`reversals` pivots).
    moment : (3, 3) float64
        The surface's second moment about ``centre``, part frame, mm²
        (the outline's axes in :meth:`outline_turns`); zero when unknown.
    """

    transforms: F64
    mean_gap_mm: F64
    mirrors: F64 = field(default_factory=lambda: np.zeros((0, 4, 4)))
    mirror_gap_mm: F64 = field(default_factory=lambda: np.zeros(0))
    centre: F64 = field(default_factory=lambda: np.zeros(3))
    moment: F64 = field(default_factory=lambda: np.zeros((3, 3)))

    def _line_of_sight(self, pose: Pose) -> tuple[F64, F64] | None:
        """The centroid ``p`` in the camera frame (mm) and the unit ray
        ``r = p / |p|`` to it, or None when it is at the camera centre."""
        p = pose.R_m2c @ self.centre + pose.t_m2c
        distance = float(np.linalg.norm(p))
        if distance == 0.0:
            return None
        return p, p / distance

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

    def reversals(self, pose: Pose) -> list[Pose]:
        """The poses that show the part mirrored, then reversed in depth.

        A point ``X`` of the part goes to ``M X`` (a near mirror symmetry),
        then ``pose`` applies, then the camera-frame reflection across the
        plane through the centroid's image ``p`` normal to its line of sight
        ``r = p / |p|``: ``S = I - 2 r r^T`` about ``p``. The rotation is
        ``S R Q`` (proper: two reflections); the centroid stays at ``p``, and
        offsets from it across the line of sight are kept while those along
        it change sign, so the outline is the same to first order.

        Parameters
        ----------
        pose : Pose
            Part frame -> camera.

        Returns
        -------
        list of Pose
            One per reflection in ``mirrors``, in order; none when the
            centroid is at the camera centre.
        """
        sight = self._line_of_sight(pose)
        if sight is None:
            return []
        p, r = sight
        R, t = pose.R_m2c, pose.t_m2c
        S = np.eye(3) - 2.0 * np.outer(r, r)
        out = []
        for M in self.mirrors:
            R_rev = S @ R @ M[:3, :3]
            # X -> S (R (Q X + m) + t - p) + p, with R_rev = S R Q.
            t_rev = S @ (R @ M[:3, 3] + t - p) + p
            out.append(Pose(reorthonormalized(R_rev), t_rev))
        return out


    def outline_turns(self, pose: Pose) -> list[Pose]:
        """The poses that show the part's outline as it is, turned over.

        A nearly ellipsoidal part's outline is nearly symmetric about its
        own two axes in the image, from any viewpoint. A half turn about
        either, through the centroid's image ``p``, keeps the outline and
        shows the part's other side, and so does a half turn about the line
        of sight (the outline turned by 180° in the image). These axes
        follow the view, not the part: no half turn about a principal axis
        of the part reaches them unless one lies across the line of sight
        (hard bench set, free-form part: most wrong poses 170-180° off the
        truth were turned about an axis within 10° of the image plane).

        The outline's axes are those of the part's second moment seen
        along the line of sight ``r``: the eigenvectors of ``P R Σ Rᵀ P``
        with ``P = I - r rᵀ`` (the outline of a weak-perspective view).

        Parameters
        ----------
        pose : Pose
            Part frame -> camera.

        Returns
        -------
        list of Pose
            The half turns about the outline's long axis, its short axis and
            the line of sight, in that order; none without a moment or when
            the centroid is at the camera centre.
        """
        sight = self._line_of_sight(pose)
        if sight is None or not np.any(self.moment):
            return []
        p, r = sight
        R, t = pose.R_m2c, pose.t_m2c
        across = np.eye(3) - np.outer(r, r)
        seen = across @ R @ self.moment @ R.T @ across
        _, vectors = np.linalg.eigh(seen)
        # eigh sorts ascending: the last two span the image plane (the
        # smallest, along r, is 0), long axis last.
        out = []
        for axis in (vectors[:, 2], vectors[:, 1], r):
            H = 2.0 * np.outer(axis, axis) - np.eye(3)
            out.append(Pose(reorthonormalized(H @ R), H @ (t - p) + p))
        return out


def near_symmetries(mesh: trimesh.Trimesh, exact: Symmetries) -> NearSymmetries:
    """The half turns about the principal axes and the reflections through the
    centroid that nearly map the part onto itself.

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
    mirrors, mirror_gaps = near_mirrors(mesh, exact, max_gap_frac=MAX_MEAN_GAP_SHARE)
    centre = surface_centroid(mesh)
    return NearSymmetries(transforms, gaps, mirrors, mirror_gaps, centre,
                          surface_second_moment(mesh, centre))
