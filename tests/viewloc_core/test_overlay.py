"""Operator overlay: the silhouette a pose gives the mesh."""

import cv2
import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from viewloc_core.camera import Camera
from viewloc_core.overlay import silhouette_mask

CAM = Camera(600.0, 600.0, 319.5, 239.5, 640, 480)


def test_a_closed_mesh_fills_its_whole_silhouette():
    """Front and back faces overlap everywhere on a closed mesh; the mask
    is their union (filled together by the even-odd rule, most of it was
    left out)."""
    box = trimesh.creation.box((100.0, 60.0, 40.0))
    R = Rotation.from_euler("xyz", [30, 40, 10], degrees=True).as_matrix()
    t = np.array([0.0, 0.0, 600.0])
    mask = silhouette_mask(CAM, R, t, box.vertices, box.faces)
    # A box's silhouette is the convex hull of its projected corners.
    hull = cv2.convexHull(CAM.project(box.vertices @ R.T + t).astype(np.float32))
    want = np.zeros_like(mask)
    cv2.fillConvexPoly(want, np.round(hull).astype(np.int32), 255)
    differ = np.count_nonzero((mask > 0) != (want > 0))
    assert np.count_nonzero(want) > 5000
    assert differ < 0.02 * np.count_nonzero(want)
