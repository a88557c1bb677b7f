"""LM-O's targets rendered at their true poses: where the real photos' losses come from.

On LM-O's real photos three things stand between the method and a part:
the clutter around it, the occluders in front of it, and the difference
between the photo of the part and the renders it was learned from (colour,
light, camera). The two diagnostic sets here take them away one at a time:

- ``lmo-composite``: each target rendered at its BOP pose (its mesh's own
  colours, the renderer's default lights) and pasted over its photo. The
  clutter stays; the occluders and the photo's own appearance of the part
  are gone.
- ``lmo-plain``: the same render over mid-grey: neither clutter nor
  occluders.

Each target becomes an image of its own (two targets of one photo are
pasted one at a time), fully visible. Read against ``lmo``: ``lmo-plain`` to
``lmo-composite`` is what the clutter costs, ``lmo-composite`` to ``lmo``
what occlusion and appearance cost. All 200 photos, learning seed 0
(``make bench`` on the core, session 58): AR_MSSD / AR_MSPD 0.876 / 0.946
plain, 0.410 / 0.493 composite, 0.128 / 0.175 real (``lmo``); 2D
recognition of the driller 0.92, 0.12 and 0.005: the clutter alone loses it.

Neither set is in the default run (``--sets lmo-composite,lmo-plain``). The
renders are written once beside the photos and read again by later runs.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import trimesh
from numpy.typing import NDArray

from model_store.files import atomic_write_bytes
from viewloc_bench.sets import BenchImage, BenchSet
from viewloc_core.camera import Camera
from viewloc_core.pose import Pose

if TYPE_CHECKING:
    from viewloc_core.render import PreparedMesh, Renderer

COMPOSITE = "lmo-composite"
PLAIN = "lmo-plain"
COMPOSITE_SETS = (COMPOSITE, PLAIN)

#: Grey level of ``lmo-plain``'s background (8-bit): mid-grey, so that a
#: dark part (the driller) and a pale one (the cat's white) both stand out.
PLAIN_GREY = 128


def _photo_rgb(path: Path) -> NDArray[np.uint8]:
    """The photo at ``path`` as (H, W, 3) uint8 RGB."""
    photo = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if photo is None:
        raise FileNotFoundError(f"cannot read the photo {path}")
    return np.ascontiguousarray(photo[:, :, ::-1])


def _pasted(renderer: Renderer, prepared: PreparedMesh, camera: Camera, pose: Pose,
            photo_rgb: NDArray[np.uint8] | None) -> NDArray[np.uint8]:
    """The part rendered at ``pose`` over ``photo_rgb`` (RGB), or over
    :data:`PLAIN_GREY` when None.

    The outline's pixels are anti-aliased: blended with the background the
    renderer draws. Pasting only the part's mask of a render over black
    would give it a dark rim one pixel wide, an edge just inside the true
    outline (the knob of the novel set over grey, 20 poses: fits a median
    3.2 % too far with the rim against 2.5 % without it at 70 px across,
    1.0 % against 0.3 % at 150 px). Over grey the renderer blends with the grey itself; over a
    photo the render over black and over white give each pixel's
    coverage, and the photo shows through the uncovered share.
    """
    if photo_rgb is None:
        grey = (PLAIN_GREY, PLAIN_GREY, PLAIN_GREY)
        return renderer.render(prepared, camera, pose, background_rgb=grey).color
    on_black = renderer.render(prepared, camera, pose,
                               background_rgb=(0, 0, 0)).color.astype(np.float64)
    on_white = renderer.render(prepared, camera, pose,
                               background_rgb=(255, 255, 255)).color.astype(np.float64)
    uncovered = np.clip((on_white - on_black) / 255.0, 0.0, 1.0)
    blended = on_black + uncovered * photo_rgb.astype(np.float64)
    return np.clip(np.rint(blended), 0, 255).astype(np.uint8)


def composite(bench: BenchSet, out_dir: Path, plain: bool) -> BenchSet:
    """The targets of ``bench`` rendered at their poses over their photos, or
    over grey.

    Parameters
    ----------
    bench : BenchSet
        From :func:`viewloc_bench.lmo.load` (coloured meshes).
    out_dir : Path
        Where the images are written, ``<object>_<photo name>``; an image
        already there is kept (written atomically, so it is whole).
    plain : bool
        Over mid-grey (:data:`PLAIN_GREY`) instead of the photo.

    Returns
    -------
    BenchSet
        Named :data:`PLAIN` or :data:`COMPOSITE`; one image per target (the
        negatives are left out: they are ``lmo``'s photos unchanged), each
        target fully visible, the same objects and camera.
    """
    from viewloc_core.render import Renderer, prepare

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    wanted = [(image, target) for image in bench.images for target in image.targets
              if target.pose is not None]
    paths = [out_dir / f"{target.object_name}_{image.path.name}" for image, target in wanted]
    missing = [(image, target, path) for (image, target), path in zip(wanted, paths, strict=True)
               if not path.exists()]
    if missing:
        prepared = {}
        with Renderer() as renderer:
            for image, target, path in missing:
                assert target.pose is not None
                if target.object_name not in prepared:
                    mesh = trimesh.load(bench.objects[target.object_name].mesh_path,
                                        force="mesh")
                    assert isinstance(mesh, trimesh.Trimesh)
                    prepared[target.object_name] = prepare(mesh)
                photo_rgb = None if plain else _photo_rgb(image.path)
                pasted = _pasted(renderer, prepared[target.object_name], image.camera, target.pose,
                                 photo_rgb)
                # OpenCV writes BGR.
                ok, png = cv2.imencode(".png", np.ascontiguousarray(pasted[:, :, ::-1]))
                if not ok:
                    raise RuntimeError(f"cannot encode {path.name}")
                atomic_write_bytes(path, png.tobytes())
    images = [BenchImage(path, image.camera, (replace(target, visible_fraction=1.0),))
              for (image, target), path in zip(wanted, paths, strict=True)]
    return BenchSet(PLAIN if plain else COMPOSITE, bench.folder, bench.objects, images,
                    bench.generation_s, {**bench.meta, "pasted_over": "grey" if plain
                                         else "photo"})
