"""The learning tasks the service queues (job kinds ``learn_mesh``, ``learn_images``).

Each reads the object's verified upload from the store, calls the engine and
returns the model; :func:`app.jobs.execute.execute_job` stores it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from model_store import JobRecord, ModelStore
from model_store.files import decode_arrays
from viewloc_core.camera import Camera
from viewloc_core.errors import InvalidInputError


def camera_from_meta(meta: dict[str, Any]) -> Camera:
    """Camera from the JSON-able dict the upload routes store."""
    return Camera(
        float(meta["fx"]), float(meta["fy"]), float(meta["cx"]), float(meta["cy"]),
        int(meta["width"]), int(meta["height"]),
        tuple(float(c) for c in meta.get("dist") or ()),
    )


def learn_mesh(
    store: ModelStore,
    job: JobRecord,
    progress: Callable[[str, float], None],
    should_stop: Callable[[], bool],
) -> Any:
    """Learn an object model from its uploaded mesh (paper §4.1)."""
    from viewloc_core.learn import LearningConfig, learn_from_mesh
    from viewloc_core.mesh import load_mesh, mesh_diameter_mm, mesh_reach_mm
    from viewloc_core.symmetry import declared_symmetries

    data, record = store.read_upload(job.object_id)
    meta = record.upload_meta
    progress("loading mesh", 0.0)
    mesh = load_mesh(data, str(meta["file_type"]), str(meta["units"]))
    config = LearningConfig.from_dict(dict(meta.get("learning") or {}))
    # Checked and converted to mm by the upload route; None means "detect".
    declared = meta.get("symmetries")
    symmetries = None if declared is None else declared_symmetries(
        declared, diameter_mm=float(mesh_diameter_mm(mesh)), reach_mm=mesh_reach_mm(mesh))
    # rng=None: the seed is ``learning.seed`` of the upload's spec (default 0).
    return learn_from_mesh(mesh, config, progress=progress, rng=None, should_stop=should_stop,
                           symmetries=symmetries)


def learn_images(
    store: ModelStore,
    job: JobRecord,
    progress: Callable[[str, float], None],
    should_stop: Callable[[], bool],
) -> Any:
    """Learn an object model from real images with known viewing angles (paper §4.1)."""
    from viewloc_core.learn import (
        LearningConfig,
        TrainingView,
        learn_from_images,
        with_symmetries,
    )
    from viewloc_core.symmetry import declared_symmetries

    data, record = store.read_upload(job.object_id)
    meta = record.upload_meta
    arrays = decode_arrays(data, "stored image set")
    n = int(meta["count"])
    images = [arrays[f"image_{i:04d}"] for i in range(n)]
    masks: list[np.ndarray] | None = None
    if meta.get("has_masks"):
        masks = [arrays[f"mask_{i:04d}"] for i in range(n)]
    views = [
        TrainingView(
            azimuth_deg=float(v["azimuth_deg"]),
            polar_deg=float(v["polar_deg"]),
            distance_mm=float(v["distance_mm"]),
            inplane_deg=float(v.get("inplane_deg", 0.0)),
        )
        for v in meta["views"]
    ]
    if len(views) != n:
        raise InvalidInputError("stored views do not match the stored images", "views")
    config = LearningConfig.from_dict(dict(meta.get("learning") or {}))
    camera = camera_from_meta(meta["camera"])
    if camera.has_distortion:
        # The engine takes pinhole images: remove the lens distortion (same K).
        from viewloc_core.camera import undistort

        progress("removing lens distortion", 0.0)
        distorted = camera
        images = [undistort(img, distorted)[0] for img in images]
        if masks is not None:
            masks = [undistort(m, distorted, nearest=True)[0] for m in masks]
        camera = Camera(distorted.fx, distorted.fy, distorted.cx, distorted.cy,
                        distorted.width, distorted.height)
    model = learn_from_images(
        images, masks, camera, views, float(meta["diameter_mm"]),
        config, progress=progress, rng=None, should_stop=should_stop,
    )
    declared = meta.get("symmetries")
    if declared is None:
        return model
    return with_symmetries(model, declared_symmetries(
        declared, diameter_mm=float(meta["diameter_mm"]), reach_mm=float(meta["diameter_mm"])))
