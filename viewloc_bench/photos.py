"""Masked training photos of a bench object, rendered: the from-images path on the bench.

A station without a CAD mesh photographs its part from known viewing angles
and sends the photos with masks (``POST /v1/objects/from-images``, the
paper's own real-image path). The ``-photos`` sets (``hard-photos``) measure
that path on a generated set's scenes: each part is learned from
:func:`render_photos` instead of its mesh, and localized in the same scenes.

The photos are what a photo station takes:

- viewpoints spread evenly over the whole sphere (a golden-angle spiral, so
  any count is even, not only the view sphere's 42, 162, 642), the mesh's
  origin on the optical axis, the camera turned about its axis by up to
  :data:`INPLANE_MAX_DEG`;
- the part :data:`PART_SPAN_PX` pixels across at the photo camera's 640×480,
  on a plain backdrop of a random colour, under random lights, with sensor
  noise; the masks are the renderer's (a chroma key's, a perfect one).

The part's colour and finish are drawn anew for every photo, from the scenes'
own palette (:func:`viewloc_bench.scenes.random_colour`). A generated set
gives its part a random material in every scene, so no one colour is the
part's: photos of one colour would teach the colour cue a colour the scenes
do not show, and the set would measure that mismatch instead of the method.
With the colours drawn like the scenes', the cue learns that the part may be
any colour, as it is in these scenes.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import trimesh
from numpy.typing import NDArray

from viewloc_bench.localizers import LearnedObject, PhotoLearningBackend
from viewloc_bench.scenes import random_colour
from viewloc_bench.sets import BenchObject
from viewloc_core.camera import Camera
from viewloc_core.view_sphere import angles_from_direction, spiral_directions

if TYPE_CHECKING:
    # The engine is imported where photos are made: the bench must load without it.
    from viewloc_core.learn import TrainingView

#: The photo station's camera (pinhole, 640×480).
PHOTO_CAMERA = Camera(800.0, 800.0, 319.5, 239.5, 640, 480)

#: The part's diameter in a photo, pixels (drawn per photo within this range).
PART_SPAN_PX = (180.0, 260.0)

#: Largest turn of the camera about its axis, degrees (either way).
INPLANE_MAX_DEG = 40.0

#: Standard deviation of the sensor noise added to every channel, grey levels.
NOISE_STD = 2.0

#: Share of photos whose part has a metallic finish (the hard set's scenes: 0.5).
METAL_SHARE = 0.5

#: Default number of photos of a ``-photos`` set: the view sphere's level 2.
DEFAULT_PHOTOS = 162


@dataclass(frozen=True, slots=True)
class TrainingPhotos:
    """Photos of one part with their masks and known viewpoints.

    Attributes
    ----------
    images : list of (H, W, 3) uint8
        RGB photos.
    masks : list of (H, W) uint8
        255 on the part, 0 elsewhere.
    views : list of TrainingView
        One per photo (the API's ``spec.views``).
    camera : Camera
        The photos' intrinsics.
    diameter_mm : float
        The part's diameter (the API's ``spec.object_diameter_mm``).
    """

    images: list[NDArray[np.uint8]]
    masks: list[NDArray[np.uint8]]
    views: list[TrainingView]
    camera: Camera
    diameter_mm: float

    def digest(self) -> str:
        """SHA-256 over the photos, masks and views (equal digests: equal photos)."""
        h = hashlib.sha256()
        for image, mask, view in zip(self.images, self.masks, self.views, strict=True):
            h.update(image.tobytes())
            h.update(mask.tobytes())
            h.update(repr((view.azimuth_deg, view.polar_deg, view.distance_mm,
                           view.inplane_deg)).encode())
        return h.hexdigest()


def render_photos(obj: BenchObject, count: int = DEFAULT_PHOTOS, seed: int = 0,
                  camera: Camera = PHOTO_CAMERA) -> TrainingPhotos:
    """Render ``count`` masked training photos of ``obj`` (see the module's docstring).

    Parameters
    ----------
    obj : BenchObject
        Its mesh (mm) and diameter.
    count : int
        Number of photos.
    seed : int
        Seed of the lights, backdrops, colours, distances and turns.
    camera : Camera
        The photos' intrinsics.

    Returns
    -------
    TrainingPhotos
    """
    from viewloc_core.learn import TrainingView
    from viewloc_core.render import Material, Renderer, prepare, random_lights

    mesh = trimesh.load(obj.mesh_path, force="mesh")
    assert isinstance(mesh, trimesh.Trimesh)
    rng = np.random.default_rng([seed, count, 20261128])
    prepared = prepare(mesh)
    images: list[NDArray[np.uint8]] = []
    masks: list[NDArray[np.uint8]] = []
    views: list[TrainingView] = []
    with Renderer() as renderer:
        for direction in spiral_directions(count):
            azimuth_deg, polar_deg = angles_from_direction(direction)
            span_px = rng.uniform(*PART_SPAN_PX)
            view = TrainingView(azimuth_deg, polar_deg,
                                float(camera.fx * obj.diameter_mm / span_px),
                                float(rng.uniform(-INPLANE_MAX_DEG, INPLANE_MAX_DEG)))
            metal = rng.uniform() < METAL_SHARE
            material = Material(random_colour(rng), metallic=float(rng.uniform(0.6, 1.0)) if metal
                                else 0.0, roughness=float(rng.uniform(0.2, 0.8)))
            red, green, blue = (int(c) for c in rng.integers(30, 220, 3))
            rendered = renderer.render(prepared, camera, view.pose(),
                                       lights=random_lights(rng), material=material,
                                       background_rgb=(red, green, blue))
            noisy = rendered.color + rng.normal(0.0, NOISE_STD, rendered.color.shape)
            images.append(np.clip(np.rint(noisy), 0, 255).astype(np.uint8))
            masks.append(np.where(rendered.mask, 255, 0).astype(np.uint8))
            views.append(view)
    return TrainingPhotos(images, masks, views, camera, obj.diameter_mm)


class PhotoBackend:
    """Learns each object from :func:`render_photos` through another backend.

    Parameters
    ----------
    backend : PhotoLearningBackend
        The core or the HTTP service (``learn_photos``).
    count : int
        Photos per object.
    seed : int
        Seed of the photos.
    """

    def __init__(self, backend: PhotoLearningBackend, count: int = DEFAULT_PHOTOS,
                 seed: int = 0) -> None:
        self.backend = backend
        self.count = count
        self.seed = seed
        self.label = f"{backend.label}, parts learned from {count} masked photos"

    def check(self) -> None:
        self.backend.check()

    def learn(self, obj: BenchObject) -> LearnedObject:
        """Render ``obj``'s photos, learn from them; the learning time excludes rendering."""
        t0 = time.perf_counter()
        photos = render_photos(obj, self.count, self.seed)
        render_s = time.perf_counter() - t0
        learned = self.backend.learn_photos(obj, photos)
        learned.info.update({"photos": self.count, "photos_render_s": round(render_s, 2)})
        return learned
