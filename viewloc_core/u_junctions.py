"""U-junctions: two corners at the two ends of one segment, turning the same way.

The next grouping above the L-junction in Pope & Lowe's hierarchy: a base
segment with an arm at each end, both on the same side of it (three sides
of a rectangle: the end of a plate, a slot, the face of a box seen at an
angle). It spans a larger part of the outline than either corner, so one
pairing fixes position, orientation and scale more firmly, and clutter
rarely forms the same pair of angles on the same side of a base.

Position: the middle of the base (between the two corners); orientation:
the base's normal towards the arms, in [0, 2π); scale: the base length.
Attributes, both similarity-invariant: the mean and the half difference of
the two interior angles (each the opening angle of its L-junction), so the
order of the corners does not matter.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]

#: Shortest base, pixels: two corners closer than this are one corner.
MIN_BASE_PX = 3.0


def _unit(v: F64) -> F64:
    return np.asarray(v / np.linalg.norm(v, axis=1, keepdims=True), np.float64)


def u_junctions(
    segments: F32, meeting_ends: NDArray[np.int64], vertex: F64
) -> tuple[F32, F32, F32, F32]:
    """U-junctions from the L-junctions of a set of segments.

    Parameters
    ----------
    segments : (S, 4) float32
        Segment end points ``x1, y1, x2, y2``, pixels.
    meeting_ends : (J, 2) int64
        Per L-junction, its two meeting segment ends as rows of
        ``[starts; ends]`` (``e < S``: start of segment ``e``, else end of
        segment ``e - S``).
    vertex : (J, 2) float64
        Corner of each L-junction, pixels.

    Returns
    -------
    xy : (U, 2) float32
        Middle of the base, pixels.
    theta : (U,) float32
        Direction of the base's normal towards the arms, radians in [0, 2π).
    scale : (U,) float32
        Base length (distance between the corners), pixels.
    attrs : (U, 2) float32
        Mean and half difference of the two interior angles, radians.
    """
    n = len(segments)
    empty = (np.zeros((0, 2), np.float32), np.zeros(0, np.float32), np.zeros(0, np.float32),
             np.zeros((0, 2), np.float32))
    if len(meeting_ends) < 2:
        return empty
    ends = np.concatenate([segments[:, :2], segments[:, 2:]]).astype(np.float64)
    # Each junction once per segment it joins: (junction, its end on that
    # segment, the other segment's end there).
    junction = np.concatenate([np.arange(len(meeting_ends))] * 2)
    own = np.concatenate([meeting_ends[:, 0], meeting_ends[:, 1]])
    other = np.concatenate([meeting_ends[:, 1], meeting_ends[:, 0]])
    at_start = own < n
    segment = np.where(at_start, own, own - n)
    # Pair every junction at a segment's start with every one at its end.
    s_idx = np.flatnonzero(at_start)
    e_idx = np.flatnonzero(~at_start)
    e_idx = e_idx[np.argsort(segment[e_idx], kind="stable")]
    e_seg = segment[e_idx]
    lo = np.searchsorted(e_seg, segment[s_idx], side="left")
    hi = np.searchsorted(e_seg, segment[s_idx], side="right")
    count = hi - lo
    if not count.any():
        return empty
    first = np.repeat(s_idx, count)
    offsets = np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
    second = e_idx[np.repeat(lo, count) + offsets]
    # Two different arms (a segment joined at both ends to one other segment
    # is a closed loop of two, not a U).
    arm1, arm2 = other[first], other[second]
    seg1 = np.where(arm1 < n, arm1, arm1 - n)
    seg2 = np.where(arm2 < n, arm2, arm2 - n)
    keep = seg1 != seg2
    first, second, arm1, arm2 = first[keep], second[keep], arm1[keep], arm2[keep]
    v1, v2 = vertex[junction[first]], vertex[junction[second]]
    base_vec = v2 - v1
    base = np.linalg.norm(base_vec, axis=1)
    keep = base >= MIN_BASE_PX
    v1, v2, base, base_vec = v1[keep], v2[keep], base[keep], base_vec[keep]
    arm1, arm2 = arm1[keep], arm2[keep]
    if len(base) == 0:
        return empty
    # Arms point from the corner to the far end of their segment.
    far1 = ends[np.where(arm1 < n, arm1 + n, arm1 - n)]
    far2 = ends[np.where(arm2 < n, arm2 + n, arm2 - n)]
    u1, u2 = _unit(far1 - v1), _unit(far2 - v2)
    b = base_vec / base[:, None]
    side1 = b[:, 0] * u1[:, 1] - b[:, 1] * u1[:, 0]
    side2 = b[:, 0] * u2[:, 1] - b[:, 1] * u2[:, 0]
    u_shaped = side1 * side2 > 0  # both arms on the same side (else a Z)
    if not u_shaped.any():
        return empty
    b, u1, u2, side1 = b[u_shaped], u1[u_shaped], u2[u_shaped], side1[u_shaped]
    v1, v2, base = v1[u_shaped], v2[u_shaped], base[u_shaped]
    alpha1 = np.arccos(np.clip((b * u1).sum(axis=1), -1.0, 1.0))
    alpha2 = np.arccos(np.clip(-(b * u2).sum(axis=1), -1.0, 1.0))
    normal = np.stack([-b[:, 1], b[:, 0]], axis=1) * np.sign(side1)[:, None]
    theta = np.mod(np.arctan2(normal[:, 1], normal[:, 0]), 2 * np.pi)
    attrs = np.stack([(alpha1 + alpha2) / 2, np.abs(alpha1 - alpha2) / 2], axis=1)
    return (((v1 + v2) / 2).astype(np.float32), theta.astype(np.float32),
            base.astype(np.float32), attrs.astype(np.float32))
