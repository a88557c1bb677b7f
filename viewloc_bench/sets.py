"""Benchmark sets: generation of the POV-Ray sets into a cache folder, and loading.

A generated set lives in ``<root>/<name>-<hash>/`` where the hash covers the
generator version, the seed and every parameter, so a folder is reused only
when it would be generated identically. It holds the images (PNG), the
visible masks of the target (``mask_visib/<image stem>.png``; of its copies
in multi-instance sets, ``mask_visib/<image stem>_c<k>.png``, k = 1, 2, ...)
and ``gt.json``::

    {"generator_version", "name", "seed", "params", "generation_s",
     "camera": {"fx", "fy", "cx", "cy", "width", "height", "K"},
     "objects": {name: {"mesh": file name in viewloc_bench/assets, "diameter_mm",
                        "symmetries_discrete": [[16 numbers], ...],
                        "symmetries_continuous": [{"axis", "offset"}, ...]}},
     "images": [{"file", "object", "present", "n_clutter", "R", "t_mm",
                 "visible_fraction", "distance_mm", "material", "background",
                 "lights", "fog", "copies"}, ...]}

``copies`` (multi-instance sets only) lists the target's copies in the image,
each ``{"R", "t_mm", "visible_fraction", "distance_mm"}``.

Every image has its own random generator seeded from (seed, set, object,
N, index): the quick subset is the first images of the full set, and the set
does not depend on the number of parallel workers.
"""

from __future__ import annotations

import hashlib
import io
import json
import shutil
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import trimesh
from numpy.typing import NDArray
from PIL import Image

from model_store.files import atomic_write_bytes
from viewloc_bench import povray as pv
from viewloc_bench import scenes, shapes
from viewloc_core.camera import Camera
from viewloc_core.metrics import symmetry_transforms
from viewloc_core.pose import Pose, orthonormalize

Array = NDArray[np.float64]

GENERATOR_VERSION = "1"
SET_CODES = {"paper": 1, "hard": 2, "novel": 3, "multi": 4, "shop": 5}


@dataclass(frozen=True, slots=True)
class SetSpec:
    """Parameters of a generated set (all of them enter the cache hash)."""

    name: str
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    objects: tuple[str, ...]
    n_values: tuple[int, ...]
    images_per_n: int
    negatives: int
    scene: scenes.SceneParams = field(default_factory=scenes.SceneParams)
    antialias: float = 0.3
    #: Instances of the object in each image that has it: the target and
    #: ``copies - 1`` copies of it.
    copies: int = 1

    @property
    def camera(self) -> Camera:
        return Camera(self.fx, self.fy, self.cx, self.cy, self.width, self.height)


def paper_spec(images_per_n: int = 10, negatives: int = 10, scale: float = 1.0) -> SetSpec:
    """The paper's set (§5.1): the barbell among N = 0..9 clutter objects at 384×288.

    ``scale`` shrinks the image and focal length together (tests use tiny images).
    """
    return SetSpec(
        "paper",
        round(384 * scale),
        round(288 * scale),
        500.0 * scale,
        500.0 * scale,
        190.7 * scale,
        144.2 * scale,
        ("barbell",),
        tuple(range(10)),
        images_per_n,
        negatives,
        scenes.SceneParams(),
    )


def hard_spec(images_per_n: int = 10, negatives: int = 6, scale: float = 1.0) -> SetSpec:
    """The hard set: bracket and free-form blob at 640×480, textures, metal, fog."""
    return SetSpec(
        "hard",
        round(640 * scale),
        round(480 * scale),
        620.0 * scale,
        620.0 * scale,
        322.4 * scale,
        238.1 * scale,
        ("bracket", "freeform"),
        (0, 2, 4, 6),
        images_per_n,
        negatives,
        scenes.SceneParams(
            distance_mm=(450.0, 1000.0),
            metal_prob=0.5,
            floor_prob=0.9,
            textured_prob=0.85,
            fog_prob=0.25,
        ),
    )


def novel_spec(images_per_n: int = 10, negatives: int = 4, scale: float = 1.0) -> SetSpec:
    """The novel set: tee, clamp and knob in the hard set's scenes (camera, textures, metal, fog).

    A generalisation check: the localizer's settings were tuned on the
    barbell, the bracket and the blob, never on these objects, so the gap
    between this set and the hard set is what the tuning does not carry over.
    """
    return replace(
        hard_spec(images_per_n, negatives, scale),
        name="novel",
        objects=("tee", "clamp", "knob"),
        n_values=(0, 2, 4, 6),
    )


def multi_spec(images_per_n: int = 8, negatives: int = 0, scale: float = 1.0) -> SetSpec:
    """The multi set: three copies of one part per image in the hard set's scenes.

    Bracket and clamp, N = 0 and 4 clutter objects. Measures finding several
    instances at once (``max_detections`` = 3): each copy lies apart from the
    others and keeps the visible fraction of the occlusion rule
    (:mod:`viewloc_bench.scenes`). No negatives by default: the other sets
    measure false positives.
    """
    return replace(
        hard_spec(images_per_n, negatives, scale),
        name="multi",
        objects=("bracket", "clamp"),
        n_values=(0, 4),
        copies=3,
    )


def shop_spec(images_per_n: int = 10, negatives: int = 4, scale: float = 1.0) -> SetSpec:
    """The shop set: hex bolt, stepped shaft and sheet-metal plate in the hard set's scenes.

    A second generalisation check, added after the localizer's settings
    had been tuned on every other set: shapes common on a shop floor that
    the others lack (a sixfold symmetry, a turned part with no cue to its
    turn, a thin flat part).
    """
    return replace(
        hard_spec(images_per_n, negatives, scale),
        name="shop",
        objects=("hexbolt", "shaft", "plate"),
        n_values=(0, 2, 4, 6),
    )


class SpecFactory(Protocol):
    """A set's parameters at a size: ``paper_spec``, ``hard_spec``, ``novel_spec``, ..."""

    def __call__(
        self, images_per_n: int = ..., negatives: int = ..., scale: float = ...
    ) -> SetSpec: ...


#: The generated sets by name, each called without sizes for its full size.
SPECS: dict[str, SpecFactory] = {
    "paper": paper_spec,
    "hard": hard_spec,
    "novel": novel_spec,
    "multi": multi_spec,
    "shop": shop_spec,
}


@dataclass(frozen=True, slots=True)
class BenchObject:
    """An object to learn and find.

    Attributes
    ----------
    name : str
    mesh_path : Path
        Mesh file in mm.
    diameter_mm : float
    symmetries : (K, 4, 4) float64
        Symmetry transforms incl. identity (continuous ones every 1°).
    pts_obj : (N, 3) float64
        Model vertices for MSSD/MSPD/ADD-S, mm.
    """

    name: str
    mesh_path: Path
    diameter_mm: float
    symmetries: Array
    pts_obj: Array


@dataclass(frozen=True, slots=True)
class Target:
    """One object instance to find in an image (``pose`` None: a negative, the object is absent)."""

    object_name: str
    pose: Pose | None
    group: str
    n_clutter: int | None = None
    visible_fraction: float | None = None
    conditions: dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class BenchImage:
    """One test image with its camera and targets."""

    path: Path
    camera: Camera
    targets: tuple[Target, ...]


@dataclass(slots=True)
class BenchSet:
    """A loaded set."""

    name: str
    folder: Path
    objects: dict[str, BenchObject]
    images: list[BenchImage]
    generation_s: float = 0.0
    meta: dict[str, Any] = field(default_factory=dict)


def unshadowed(spec: SetSpec) -> SetSpec:
    """The set's scenes with objects that cast no shadow
    (:attr:`viewloc_bench.scenes.SceneParams.cast_shadows`): the same draws,
    another folder."""
    return replace(spec, scene=replace(spec.scene, cast_shadows=False))


def spec_params(spec: SetSpec) -> dict[str, Any]:
    """The parameters that name a set (hashed) and are recorded in its ``gt.json``."""
    params = asdict(spec)
    if spec.copies == 1:
        # Sets of one instance per image were hashed before ``copies`` existed:
        # leaving the key out keeps their cached folders' names and gt.json.
        del params["copies"]
    if spec.scene.cast_shadows:
        # The same for the scenes' shadows, cast in every set before the
        # key existed.
        del params["scene"]["cast_shadows"]
    return params


def spec_hash(spec: SetSpec, seed: int) -> str:
    """Hash of generator version, seed and parameters (12 hex digits)."""
    blob = json.dumps(
        {"version": GENERATOR_VERSION, "seed": seed, "spec": spec_params(spec)}, sort_keys=True
    )
    return hashlib.sha256(blob.encode()).hexdigest()[:12]


def _image_rng(seed: int, spec: SetSpec, obj_idx: int, n: int, i: int) -> np.random.Generator:
    code = n if n >= 0 else 1000  # negatives
    return np.random.default_rng(
        np.random.SeedSequence([seed, SET_CODES[spec.name], obj_idx, code, i])
    )


def _jobs(spec: SetSpec) -> list[tuple[int, int, int, bool]]:
    """(object index, N, image index, object present) per image, in file order."""
    jobs = [
        (oi, n, i, True)
        for oi in range(len(spec.objects))
        for n in spec.n_values
        for i in range(spec.images_per_n)
    ]
    # Negatives: clutter only, N drawn from the upper half of the set's range.
    jobs += [(oi, -1, i, False) for oi in range(len(spec.objects)) for i in range(spec.negatives)]
    return jobs


def asset_digest(name: str) -> str:
    """SHA-256 (hex) of a benchmark object's committed mesh file."""
    return hashlib.sha256(shapes.asset_path(name).read_bytes()).hexdigest()


def _object_entry(name: str) -> dict[str, Any]:
    shape = shapes.SHAPES[name]()
    mesh = shapes.to_trimesh(shape)
    return {
        "mesh": shapes.ASSET_FILES[name],
        # The set's name hashes its parameters, not its objects' shapes; a
        # set is learned from the committed meshes (load_generated), so one
        # drawn with other meshes must be drawn anew (_drawn_with_current_meshes).
        "mesh_sha256": asset_digest(name),
        "diameter_mm": shapes.diameter_mm(mesh),
        "symmetries_discrete": [np.asarray(s).reshape(-1).tolist() for s in shape.sym_discrete],
        "symmetries_continuous": [
            {"axis": np.asarray(a).tolist(), "offset": np.asarray(o).tolist()}
            for a, o in shape.sym_continuous
        ],
    }


def _render_one(
    spec: SetSpec, seed: int, job: tuple[int, int, int, bool], folder: Path, threads: int
) -> dict[str, Any]:
    oi, n, i, present = job
    name = spec.objects[oi]
    rng = _image_rng(seed, spec, oi, n, i)
    camera = spec.camera
    shape = shapes.SHAPES[name]()
    pts = np.asarray(shapes.to_trimesh(shape).convex_hull.vertices, dtype=np.float64)
    if not present:
        n = int(rng.integers(max(spec.n_values) // 2, max(spec.n_values) + 1))
    scene = scenes.draw_scene(
        rng,
        camera,
        shape if present else None,
        pts if present else None,
        n,
        spec.scene,
        copies=spec.copies - 1 if present else 0,
    )
    masks, visible = _visible_masks(spec, scene, rng, n, threads) if present else ([], [])
    img = pv.render(
        scenes.scene_sdl(scene, "color"),
        camera.width,
        camera.height,
        antialias=spec.antialias,
        threads=threads,
    )
    stem = f"{name}_n{n:02d}_{i:03d}" if present else f"{name}_neg_{i:03d}"
    Image.fromarray(img).save(folder / f"{stem}.png", optimize=False)
    entry: dict[str, Any] = {
        "file": f"{stem}.png",
        "object": name,
        "present": present,
        "n_clutter": len(scene.clutter),
        "background": scene.background_kind,
        "lights": len(scene.lights),
        "fog": bool(scene.fog_sdl),
    }
    if present and scene.target is not None:
        for k, mask in enumerate(masks):
            mask_stem = stem if k == 0 else f"{stem}_c{k}"
            Image.fromarray((mask * 255).astype(np.uint8)).save(
                folder / "mask_visib" / f"{mask_stem}.png"
            )
        entry.update(_instance_entry(scene.target, visible[0]), material=scene.material)
        if scene.copies:
            entry["copies"] = [
                _instance_entry(c, v) for c, v in zip(scene.copies, visible[1:], strict=True)
            ]
    return entry


def _instance_entry(placed: scenes.Placed, visible: float) -> dict[str, Any]:
    """``gt.json`` fields of one instance: pose, visible fraction, distance (mm)."""
    return {
        "R": placed.pose.R_m2c.tolist(),
        "t_mm": placed.pose.t_m2c.tolist(),
        "visible_fraction": round(visible, 4),
        "distance_mm": float(np.linalg.norm(placed.pose.t_m2c)),
    }


def _visible_masks(
    spec: SetSpec, scene: scenes.Scene, rng: np.random.Generator, n: int, threads: int
) -> tuple[list[NDArray[np.bool_]], list[float]]:
    """Visible masks and fractions of every instance, re-drawing the clutter until
    each keeps ``min_visible`` (the occlusion rule in :mod:`viewloc_bench.scenes`).

    Returns
    -------
    masks : list of (H, W) bool arrays
        One per instance of :attr:`scenes.Scene.instances` (the target first).
    visible : list of float
        Their visible fractions (pixels kept over pixels rendered alone).
    """
    instances = scene.instances
    alone = [scenes.target_mask(scene, threads, focus=k) for k in range(len(instances))]
    # With one instance and no clutter nothing can hide it: its alone-mask is
    # its visible mask (a render saved, as before copies existed).
    single = len(instances) == 1
    masks, visible = alone, [1.0] * len(instances)
    for attempt in range(scenes.MAX_CLUTTER_ATTEMPTS + 1):
        masks = [
            scenes.visible_mask(scene, threads, focus=k) if n > 0 or not single else alone[k]
            for k in range(len(instances))
        ]
        visible = [float(m.sum() / max(1, a.sum())) for m, a in zip(masks, alone, strict=True)]
        if min(visible) >= spec.scene.min_visible:
            break
        behind = attempt + 1 >= scenes.MAX_CLUTTER_ATTEMPTS
        scene.clutter = scenes.sample_clutter(
            rng, spec.camera, n, spec.scene, instances, behind_only=behind
        )
    return masks, visible


def generate(
    spec: SetSpec,
    seed: int,
    root: Path,
    workers: int = 3,
    threads: int = 1,
    log: Callable[[str], None] | None = print,
) -> Path:
    """Generate a set into ``root/<name>-<hash>/`` unless it is already there,
    drawn with the objects' committed meshes (else it is drawn anew).

    Parameters
    ----------
    workers : int
        POV-Ray processes at a time (each spends much of its start-up idle).
    threads : int
        Render threads per process.

    Returns
    -------
    Path
        The set folder (with ``gt.json``).
    """
    folder = Path(root) / f"{spec.name}-{spec_hash(spec, seed)}"
    if (folder / "gt.json").exists():
        if _drawn_with_current_meshes(folder):
            return folder
        if log is not None:
            log(f"  {spec.name}: {folder.name} was drawn with other meshes: drawing it anew")
    tmp = folder.with_name(folder.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "mask_visib").mkdir(parents=True)
    jobs = _jobs(spec)
    t0 = time.perf_counter()
    done = 0
    entries: list[dict[str, Any]] = []
    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        futures = [pool.submit(_render_one, spec, seed, j, tmp, threads) for j in jobs]
        for fut in futures:
            entries.append(fut.result())
            done += 1
            if log is not None and (done % 10 == 0 or done == len(jobs)):
                log(f"  {spec.name}: {done}/{len(jobs)} images, {time.perf_counter() - t0:.0f} s")
    elapsed = time.perf_counter() - t0
    cam = spec.camera
    gt = {
        "generator_version": GENERATOR_VERSION,
        "name": spec.name,
        "seed": seed,
        "params": spec_params(spec),
        "generation_s": round(elapsed, 2),
        "camera": {
            "fx": cam.fx,
            "fy": cam.fy,
            "cx": cam.cx,
            "cy": cam.cy,
            "width": cam.width,
            "height": cam.height,
            "K": cam.K.tolist(),
        },
        "objects": {name: _object_entry(name) for name in spec.objects},
        "images": entries,
    }
    (tmp / "gt.json").write_text(json.dumps(gt, indent=1))
    shutil.rmtree(folder, ignore_errors=True)
    tmp.rename(folder)
    return folder


def _drawn_with_current_meshes(folder: Path) -> bool:
    """Whether a generated set's images show its objects' committed meshes:
    each object's recorded ``mesh_sha256`` is theirs. Sets drawn before the
    digest was recorded pass: nothing was recorded to check them against."""
    gt = json.loads((folder / "gt.json").read_text())
    return all(entry.get("mesh_sha256") in (None, asset_digest(name))
               for name, entry in gt["objects"].items())


def load_object(
    name: str,
    mesh_path: Path,
    diameter_mm: float,
    sym_discrete: list[list[float]],
    sym_continuous: list[dict[str, list[float]]],
) -> BenchObject:
    """A BenchObject from a mesh file and BOP-style symmetry annotations."""
    mesh = trimesh.load(mesh_path, force="mesh", process=False)
    assert isinstance(mesh, trimesh.Trimesh)
    syms = symmetry_transforms(
        [np.asarray(s, dtype=np.float64).reshape(4, 4) for s in sym_discrete],
        [(np.asarray(c["axis"]), np.asarray(c["offset"])) for c in sym_continuous],
        step_deg=1.0,
    )
    return BenchObject(
        name,
        Path(mesh_path),
        float(diameter_mm),
        syms,
        np.asarray(mesh.vertices, dtype=np.float64),
    )


def images_digest(images: list[BenchImage]) -> str:
    """A fingerprint of a set's images: SHA-256 over each image's file name
    and decoded pixels, in the set's order (hex).

    A set folder's name fixes the generator and its parameters, not what
    the renderer makes of them on another machine: the same code measured
    hard-set AR_MSSD 0.8988 and 0.8862 at learning seed 0 on two machines,
    and without the first one's images nobody could tell whether the
    images differed. Pixels, not file bytes, are hashed, so that a PNG
    encoder's choices do not count as a change.
    """
    digest = hashlib.sha256()
    for im in images:
        with Image.open(im.path) as pil:
            pixels = np.ascontiguousarray(np.asarray(pil))
        digest.update(im.path.name.encode())
        digest.update(str(pixels.shape).encode())
        digest.update(pixels.tobytes())
    return digest.hexdigest()


#: Scene conditions of a generated image that the report breaks results down by.
CONDITION_KEYS = ("background", "material", "fog", "lights")


def _conditions(entry: dict[str, Any]) -> dict[str, str]:
    """The scene conditions recorded for one image of ``gt.json`` (older sets lack some)."""
    return {k: str(entry[k]) for k in CONDITION_KEYS if entry.get(k) is not None}


def load_generated(folder: Path) -> BenchSet:
    """Load a generated set from its folder."""
    folder = Path(folder)
    gt = json.loads((folder / "gt.json").read_text())
    c = gt["camera"]
    camera = Camera(c["fx"], c["fy"], c["cx"], c["cy"], c["width"], c["height"])
    objects = {
        name: load_object(
            name,
            shapes.ASSETS_DIR / o["mesh"],
            o["diameter_mm"],
            o["symmetries_discrete"],
            o["symmetries_continuous"],
        )
        for name, o in gt["objects"].items()
    }
    images = []
    for e in gt["images"]:
        if e["present"]:
            # The target and each of its copies: one target per instance.
            targets = tuple(
                Target(
                    e["object"],
                    Pose(orthonormalize(np.asarray(inst["R"])), np.asarray(inst["t_mm"])),
                    f"N={e['n_clutter']}", e["n_clutter"], inst["visible_fraction"],
                    _conditions(e),
                )
                for inst in [e, *e.get("copies", [])]
            )
        else:
            targets = (Target(e["object"], None, "negative", e["n_clutter"],
                              conditions=_conditions(e)),)
        images.append(BenchImage(folder / e["file"], camera, targets))
    return BenchSet(gt["name"], folder, objects, images, gt["generation_s"], gt)


#: The folder of a generated set that holds its images as a monochrome camera
#: would see them (:func:`monochrome`).
MONO_FOLDER = "mono"


def monochrome(bench: BenchSet) -> BenchSet:
    """The same set as a monochrome camera sees it: each image in grey, stored as RGB.

    Machine-vision stations mostly use monochrome cameras, and their frames
    often reach the service as RGB files with three equal channels. The grey
    is the luminance of the rendered colours (ITU-R BT.601 weights, what
    OpenCV's ``COLOR_RGB2GRAY`` computes), about what a sensor without a
    colour filter integrates: edges between colours of equal brightness
    vanish, and no colour cue is left. The images are written once into
    ``<set folder>/mono/`` (atomically; a second call reuses them); targets,
    cameras and objects are the set's own. Its name gets ``-mono``.

    Parameters
    ----------
    bench : BenchSet
        A loaded set (its images RGB or grey PNGs).

    Returns
    -------
    BenchSet
    """
    out_dir = bench.folder / MONO_FOLDER
    out_dir.mkdir(exist_ok=True)
    images = []
    for im in bench.images:
        path = out_dir / im.path.name
        if not path.exists():
            with Image.open(im.path) as pil:
                grey = pil.convert("RGB").convert("L")  # BT.601 luma
            buf = io.BytesIO()
            Image.merge("RGB", (grey, grey, grey)).save(buf, format="PNG")
            atomic_write_bytes(path, buf.getvalue())
        images.append(replace(im, path=path))
    return replace(bench, name=f"{bench.name}-mono", images=images)
