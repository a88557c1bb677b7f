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
what occlusion and appearance cost. LM-O every 4th photo, learning seed 0
(session 58, in-process): AR_MSSD / AR_MSPD 0.807 / 0.925 plain, 0.418 /
0.507 composite, 0.174 / 0.239 real; 2D recognition of the driller 0.86,
0.12 and 0.00: the clutter alone loses it.

Neither set is in the default run (``--sets lmo-composite,lmo-plain``). The
renders are written once beside the photos and read again by later runs.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import trimesh

from model_store.files import atomic_write_bytes
from viewloc_bench.sets import BenchImage, BenchSet

COMPOSITE = "lmo-composite"
PLAIN = "lmo-plain"
COMPOSITE_SETS = (COMPOSITE, PLAIN)

#: Grey level of ``lmo-plain``'s background (8-bit): mid-grey, so that a
#: dark part (the driller) and a pale one (the cat's white) both stand out.
PLAIN_GREY = 128


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
                rendered = renderer.render(prepared[target.object_name], image.camera,
                                           target.pose)
                photo = cv2.imread(str(image.path), cv2.IMREAD_COLOR)
                if photo is None:
                    raise FileNotFoundError(f"cannot read the photo {image.path}")
                pasted = (np.full_like(photo, PLAIN_GREY) if plain else photo)
                # The render is RGB; OpenCV writes BGR.
                pasted[rendered.mask] = rendered.color[rendered.mask][:, ::-1]
                ok, png = cv2.imencode(".png", pasted)
                if not ok:
                    raise RuntimeError(f"cannot encode {path.name}")
                atomic_write_bytes(path, png.tobytes())
    images = [BenchImage(path, image.camera, (replace(target, visible_fraction=1.0),))
              for (image, target), path in zip(wanted, paths, strict=True)]
    return BenchSet(PLAIN if plain else COMPOSITE, bench.folder, bench.objects, images,
                    bench.generation_s, {**bench.meta, "pasted_over": "grey" if plain
                                         else "photo"})
