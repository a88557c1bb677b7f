"""Random benchmark scenes: object pose, clutter, lights, materials, background, fog.

Everything is drawn from one ``np.random.Generator`` per image, so a scene
depends only on (seed, set, object, N, index), not on how many images are
generated or in which order.

Occlusion rule (written down once): clutter may stand in front of the
target, but the target must keep a visible fraction of at least
``min_visible`` (0.6 by default: the fraction of the target's pixels, rendered
alone, that are still target pixels with the clutter in place). Clutter is
re-drawn up to :data:`MAX_CLUTTER_ATTEMPTS` times; after that, the clutter is
drawn only behind the target (visible fraction 1). Bounding spheres of target
and clutter never intersect, and clutter objects do not intersect each other.

Copies (multi-instance scenes): a scene may hold further instances of the
target, same shape and finish (a tray of identical parts). Each lies apart
from the others, in space (bounding spheres) and in the image (the circles
about their projected origins that hold their projected hulls), so each can
be seen whole; the occlusion rule then holds for every instance, and clutter
avoids and, when drawn behind, stays behind all of them.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from viewloc_bench import povray as pv
from viewloc_bench import shapes
from viewloc_core.camera import Camera
from viewloc_core.pose import Pose

Array = NDArray[np.float64]

MAX_CLUTTER_ATTEMPTS = 6
#: Poses tried for one copy before the scene is declared impossible.
MAX_COPY_ATTEMPTS = 300
LABEL_TARGET = (1.0, 0.0, 0.0)
LABEL_CLUTTER = (0.0, 1.0, 0.0)


@dataclass(frozen=True, slots=True)
class SceneParams:
    """How a set's scenes are drawn.

    Attributes
    ----------
    distance_mm : (min, max)
        Distance of the target's origin from the camera centre.
    clutter_depth_mm : (min, max)
        Depth (camera z) of clutter centres.
    min_visible : float
        Least visible fraction of the target (module doc).
    metal_prob : float
        Probability of a specular metal finish for each object.
    floor_prob : float
        Probability of a background plane instead of a plain background.
    textured_prob : float
        Probability that a background plane carries a procedural texture.
    fog_prob : float
        Probability of fog (the paper's Fig. 4).
    margin_px : float
        The target's projection keeps this distance from the image border.
    cast_shadows : bool
        Whether the objects cast shadows (under POV-Ray's point lights they
        do). False renders the same scenes with objects that cast none: a
        diagnostic of what the cast shadows cost (bench sets
        ``*-unshadowed``). A part floating before the floor casts a copy of
        its outline there, about its own size in the image with the lights
        near the camera.
    """

    distance_mm: tuple[float, float] = (500.0, 1100.0)
    clutter_depth_mm: tuple[float, float] = (400.0, 1300.0)
    min_visible: float = 0.6
    metal_prob: float = 0.2
    floor_prob: float = 0.5
    textured_prob: float = 0.0
    fog_prob: float = 0.0
    margin_px: float = 2.0
    cast_shadows: bool = True


@dataclass(frozen=True, slots=True)
class Placed:
    """A shape at a pose (object -> camera) with its POV-Ray texture."""

    shape: shapes.Shape
    pose: Pose
    texture: str
    radius_mm: float


@dataclass(slots=True)
class Scene:
    """One drawn scene: target (or None for a negative), its copies, clutter, lights, background."""

    camera: Camera
    target: Placed | None
    clutter: list[Placed]
    lights: list[tuple[Array, tuple[float, float, float]]]
    background_sdl: str
    background_kind: str
    fog_sdl: str = ""
    material: str = ""
    info: dict[str, object] = field(default_factory=dict)
    copies: list[Placed] = field(default_factory=list)
    cast_shadows: bool = True

    @property
    def instances(self) -> list[Placed]:
        """The target and its copies (instance 0 is the target; empty for a negative)."""
        return ([self.target] if self.target is not None else []) + self.copies


def random_colour(rng: np.random.Generator, v_min: float = 0.35) -> tuple[float, float, float]:
    """A random display colour (r, g, b), each 0..1: any hue, saturation up to 0.8,
    value from ``v_min`` to 0.95 (the scenes' palette)."""
    h, s, v = rng.uniform(0, 1), rng.uniform(0.0, 0.8), rng.uniform(v_min, 0.95)
    r, g, b = colorsys.hsv_to_rgb(h, s, v)
    return (r, g, b)


def _material(rng: np.random.Generator, metal_prob: float) -> tuple[str, str]:
    """(kind, SDL texture) from matte to specular."""
    c = pv.vec(random_colour(rng))
    if rng.uniform() < metal_prob:
        rough = rng.uniform(0.003, 0.03)
        refl = rng.uniform(0.1, 0.35)
        return "metal", (
            f"texture {{ pigment {{ rgb {c} }} finish {{ ambient 0.05 diffuse 0.35 metallic "
            f"specular 0.9 roughness {rough:.4f} brilliance 2 "
            f"reflection {{ {refl:.3f} metallic }} }} }}"
        )
    kind = ["matte", "plastic", "glossy"][int(rng.integers(0, 3))]
    if kind == "matte":
        fin = f"ambient 0.12 diffuse {rng.uniform(0.6, 0.9):.3f}"
    elif kind == "plastic":
        fin = (
            f"ambient 0.1 diffuse 0.7 phong {rng.uniform(0.4, 1.0):.3f} "
            f"phong_size {rng.uniform(20, 90):.1f}"
        )
    else:
        fin = (
            f"ambient 0.08 diffuse 0.6 specular {rng.uniform(0.4, 0.8):.3f} "
            f"roughness {rng.uniform(0.005, 0.05):.4f} reflection {rng.uniform(0.03, 0.12):.3f}"
        )
    return kind, f"texture {{ pigment {{ rgb {c} }} finish {{ {fin} }} }}"


def _hull(mesh_vertices: Array) -> Array:
    return np.asarray(mesh_vertices, dtype=np.float64)


def sample_target_pose(
    rng: np.random.Generator,
    camera: Camera,
    pts_obj: Array,
    distance_mm: tuple[float, float],
    margin_px: float,
) -> Pose:
    """Rotation uniform over SO(3), distance uniform, wholly inside the image (resampled).

    Parameters
    ----------
    pts_obj : (N, 3) array
        Points whose projections must stay inside (e.g. hull vertices), mm.
    """
    for _ in range(10000):
        R = Rotation.random(random_state=rng).as_matrix()
        uv = np.array([[rng.uniform(0, camera.width - 1), rng.uniform(0, camera.height - 1)]])
        d = rng.uniform(*distance_mm)
        t = d * camera.ray(uv)[0]
        pose = Pose(R, t)
        p = pose.transform(pts_obj)
        if np.any(p[:, 2] <= 1.0):
            continue
        proj = camera.project(p)
        if (
            proj[:, 0].min() >= margin_px
            and proj[:, 1].min() >= margin_px
            and proj[:, 0].max() <= camera.width - 1 - margin_px
            and proj[:, 1].max() <= camera.height - 1 - margin_px
        ):
            return pose
    raise RuntimeError("could not place the object inside the image")


def sample_clutter_shape(rng: np.random.Generator) -> shapes.Shape:
    """Mostly rectangular bars, boxes and frames (paper §5.1), some round rods."""
    kind = rng.choice(["bar", "box", "frame", "rod"], p=[0.35, 0.2, 0.3, 0.15])
    if kind == "bar":
        return shapes.bar(rng.uniform(90, 220), rng.uniform(8, 22), rng.uniform(8, 22))
    if kind == "box":
        return shapes.box(*rng.uniform(25, 90, size=3))
    if kind == "frame":
        w = rng.uniform(7, 16)
        return shapes.frame(rng.uniform(60, 150), rng.uniform(50, 130), w, rng.uniform(6, 16))
    return shapes.rod(rng.uniform(80, 200), rng.uniform(4, 10))


def _bounding_radius(shape: shapes.Shape) -> float:
    v = np.asarray(shapes.to_trimesh(shape).vertices)
    return float(np.linalg.norm(v, axis=1).max())


def image_circle(camera: Camera, placed: Placed, pts_obj: Array) -> tuple[Array, float]:
    """The circle about an instance's projected origin that holds its projected points.

    Parameters
    ----------
    pts_obj : (N, 3) array
        The instance's hull vertices (object frame, mm): the projected hull
        holds the instance's whole silhouette.

    Returns
    -------
    centre : (2,) array
        Projected origin, px.
    radius : float
        px.
    """
    centre = camera.project(placed.pose.t_m2c[None])[0]
    uv = camera.project(placed.pose.transform(pts_obj))
    return centre, float(np.linalg.norm(uv - centre, axis=1).max())


def sample_copies(
    rng: np.random.Generator,
    camera: Camera,
    target: Placed,
    target_pts: Array,
    copies: int,
    params: SceneParams,
) -> list[Placed]:
    """``copies`` more instances of the target, each apart from the target and the others.

    Each copy is posed like the target (:func:`sample_target_pose`) and kept
    when its bounding sphere meets no other instance's and its image circle
    (:func:`image_circle`) overlaps no other instance's, so no instance hides
    another.

    Raises
    ------
    RuntimeError
        When a copy finds no free place in :data:`MAX_COPY_ATTEMPTS` poses.
    """
    placed = [target]
    circles = [image_circle(camera, target, target_pts)]
    for k in range(copies):
        for _try in range(MAX_COPY_ATTEMPTS):
            pose = sample_target_pose(rng, camera, target_pts, params.distance_mm, params.margin_px)
            candidate = Placed(target.shape, pose, target.texture, target.radius_mm)
            centre, radius = image_circle(camera, candidate, target_pts)
            apart_in_space = all(
                np.linalg.norm(pose.t_m2c - o.pose.t_m2c) > candidate.radius_mm + o.radius_mm
                for o in placed
            )
            apart_in_image = all(np.linalg.norm(centre - c) > radius + r for c, r in circles)
            if apart_in_space and apart_in_image:
                placed.append(candidate)
                circles.append((centre, radius))
                break
        else:
            raise RuntimeError(
                f"could not place copy {k + 1} of {copies} apart from the other instances "
                f"in {MAX_COPY_ATTEMPTS} poses ({camera.width}x{camera.height} image, "
                f"distance {params.distance_mm} mm)"
            )
    return placed[1:]


def sample_clutter(
    rng: np.random.Generator,
    camera: Camera,
    n: int,
    params: SceneParams,
    instances: list[Placed],
    behind_only: bool,
) -> list[Placed]:
    """``n`` clutter objects apart from ``instances`` (the target and its copies) and each other.

    ``behind_only`` puts every clutter object wholly behind the farthest
    instance, so none of them can be hidden.
    """
    out: list[Placed] = []
    for _ in range(n):
        shape = sample_clutter_shape(rng)
        r = _bounding_radius(shape)
        _, tex = _material(rng, params.metal_prob)
        for _try in range(500):
            uv = np.array([[rng.uniform(0, camera.width - 1), rng.uniform(0, camera.height - 1)]])
            z_min, z_max = params.clutter_depth_mm
            if behind_only and instances:
                far = max(o.pose.t_m2c[2] + o.radius_mm for o in instances)
                z_min = max(z_min, far + r + 1.0)
                z_max = max(z_max, z_min + 200.0)
            z = rng.uniform(z_min, z_max)
            ray = camera.ray(uv)[0]
            c = ray * (z / ray[2])
            others = instances + out
            if all(np.linalg.norm(c - o.pose.t_m2c) > r + o.radius_mm for o in others):
                R = Rotation.random(random_state=rng).as_matrix()
                out.append(Placed(shape, Pose(R, c), tex, r))
                break
    return out


def _lights(rng: np.random.Generator) -> list[tuple[Array, tuple[float, float, float]]]:
    n = int(rng.integers(1, 4))
    lights = []
    for _ in range(n):
        pos = np.array([rng.uniform(-1500, 1500), rng.uniform(-1500, 1500), rng.uniform(-800, 400)])
        h, s, v = rng.uniform(0, 1), rng.uniform(0, 0.35), rng.uniform(0.7, 1.0)
        rgb = np.array(colorsys.hsv_to_rgb(h, s, v)) * (1.3 / n**0.5)
        lights.append((pos, (float(rgb[0]), float(rgb[1]), float(rgb[2]))))
    return lights


TEXTURES = ("wood", "granite", "checker", "noise", "agate")


def _background(rng: np.random.Generator, params: SceneParams) -> tuple[str, str]:
    """(kind, SDL) of a plain background or a tilted plane behind everything."""
    if rng.uniform() >= params.floor_prob:
        return "plain", f"background {{ rgb {pv.vec(random_colour(rng, 0.1))} }}\n"
    z_bg = rng.uniform(1800, 2300)
    tilt = Rotation.from_rotvec(rng.normal(size=3) / 3 * np.radians(30)).as_matrix()
    n_cam = tilt @ np.array([0.0, 0.0, -1.0])
    if np.degrees(np.arccos(-n_cam[2])) > 30.0:
        n_cam = np.array([0.0, 0.0, -1.0])
    dist = float(-n_cam @ np.array([0.0, 0.0, z_bg]))
    kind = "floor"
    c1, c2 = pv.vec(random_colour(rng, 0.15)), pv.vec(random_colour(rng, 0.15))
    pigment = f"pigment {{ rgb {c1} }}"
    if rng.uniform() < params.textured_prob:
        kind = str(rng.choice(TEXTURES))
        scale = rng.uniform(40, 160)
        if kind == "checker":
            pigment = f"pigment {{ checker rgb {c1} rgb {c2} scale {scale:.1f} }}"
        elif kind == "wood":
            pigment = (
                f"pigment {{ wood turbulence 0.3 "
                f"color_map {{ [0 rgb {c1}] [0.7 rgb {c2}] [1 rgb {c1}] }} scale {scale:.1f} "
                f"rotate <{rng.uniform(0, 90):.1f}, {rng.uniform(0, 90):.1f}, 0> }}"
            )
        elif kind == "granite":
            pigment = (
                f"pigment {{ granite color_map {{ [0 rgb {c1}] [1 rgb {c2}] }}"
                f" scale {scale * 3:.1f} }}"
            )
        elif kind == "noise":
            pigment = (
                f"pigment {{ bozo turbulence 0.5 color_map {{ [0 rgb {c1}] [1 rgb {c2}] }}"
                f" scale {scale / 2:.1f} }}"
            )
        else:
            pigment = (
                f"pigment {{ agate agate_turb 0.6 color_map {{ [0 rgb {c1}] [1 rgb {c2}] }}"
                f" scale {scale * 2:.1f} }}"
            )
    plane = f"plane {{ {pv.cam_point(n_cam)}, {-dist:.4f} {pigment}"
    sdl = f"background {{ rgb 0 }}\n{plane} finish {{ ambient 0.1 diffuse 0.8 }} }}\n"
    return kind, sdl


def draw_scene(
    rng: np.random.Generator,
    camera: Camera,
    target_shape: shapes.Shape | None,
    target_pts: Array | None,
    n_clutter: int,
    params: SceneParams,
    behind_only: bool = False,
    copies: int = 0,
) -> Scene:
    """Draw one random scene (clutter drawn last so it can be re-drawn alone).

    Parameters
    ----------
    target_shape : Shape or None
        The object to find; None draws a negative scene of clutter only.
    target_pts : (N, 3) array or None
        The target's mesh vertices (object frame, mm).
    copies : int
        Further instances of the target (:func:`sample_copies`), drawn after
        the fog and before the clutter: with none, the generator is used
        exactly as by scenes without copies, so those scenes stay the same.
    """
    lights = _lights(rng)
    bg_kind, bg = _background(rng, params)
    fog = ""
    target = None
    material = ""
    if target_shape is not None and target_pts is not None:
        pose = sample_target_pose(rng, camera, target_pts, params.distance_mm, params.margin_px)
        material, tex = _material(rng, params.metal_prob)
        radius = float(np.linalg.norm(target_pts, axis=1).max())
        target = Placed(target_shape, pose, tex, radius)
    if rng.uniform() < params.fog_prob:
        z_ref = target.pose.t_m2c[2] if target is not None else 800.0
        fog_c = pv.vec(np.full(3, rng.uniform(0.55, 0.9)))
        fog = f"fog {{ fog_type 1 distance {z_ref * rng.uniform(1.3, 3.0):.1f} rgb {fog_c} }}\n"
    placed_copies: list[Placed] = []
    if copies > 0 and target is not None and target_pts is not None:
        placed_copies = sample_copies(rng, camera, target, target_pts, copies, params)
    instances = ([target] if target is not None else []) + placed_copies
    clutter = sample_clutter(rng, camera, n_clutter, params, instances, behind_only)
    return Scene(
        camera, target, clutter, lights, bg, bg_kind, fog, material, copies=placed_copies,
        cast_shadows=params.cast_shadows,
    )


def scene_sdl(scene: Scene, mode: str = "color", focus: int = 0) -> str:
    """POV-Ray SDL of a scene.

    ``mode`` is ``"color"`` (the test image, every instance), ``"label"``
    (the focus instance red; clutter and the other instances, its occluders,
    green; self-lit, black background, no fog) or ``"target"`` (the focus
    instance alone, labelled). ``focus`` picks the instance of
    :attr:`Scene.instances`: 0 the target, k the copy ``copies[k - 1]``.
    """
    parts = []
    if mode == "color":
        parts.append(pv.scene_header(scene.camera))
        parts.append("global_settings { ambient_light rgb 1 }\n")
        parts.append(scene.background_sdl)
        parts.append(scene.fog_sdl)
        for pos, rgb in scene.lights:
            parts.append(f"light_source {{ {pv.cam_point(pos)} color rgb {pv.vec(rgb)} }}\n")
        # POV-Ray's object modifier: the object is lit as before but casts
        # no shadow (a shadowless light would also change its highlights).
        modifier = "" if scene.cast_shadows else " no_shadow"
        for o in scene.instances + scene.clutter:
            parts.append(shapes.to_pov(o.shape, o.texture + modifier, pv.pose_matrix_sdl(o.pose))
                         + "\n")
        return "".join(parts)

    def flat(rgb: tuple[float, float, float]) -> str:
        return (
            f"texture {{ pigment {{ rgb {pv.vec(rgb)} }} "
            "finish { emission 1 diffuse 0 ambient 0 } }"
        )

    parts.append(pv.scene_header(scene.camera))
    instances = scene.instances
    if focus and not 0 <= focus < len(instances):
        raise ValueError(f"focus {focus}: the scene has {len(instances)} instances")
    if instances:
        o = instances[focus]
        parts.append(shapes.to_pov(o.shape, flat(LABEL_TARGET), pv.pose_matrix_sdl(o.pose)))
    if mode == "label":
        occluders = [o for k, o in enumerate(instances) if k != focus] + scene.clutter
        for o in occluders:
            parts.append(shapes.to_pov(o.shape, flat(LABEL_CLUTTER), pv.pose_matrix_sdl(o.pose)))
    return "\n".join(parts) + "\n"


def target_mask(scene: Scene, threads: int = 1, focus: int = 0) -> NDArray[np.bool_]:
    """(H, W) bool: the focus instance's pixels when rendered alone (``focus``: see
    :func:`scene_sdl`)."""
    W, H = scene.camera.width, scene.camera.height
    img = pv.render(scene_sdl(scene, "target", focus), W, H, antialias=None, threads=threads)
    return img[..., 0] > 127


def visible_mask(scene: Scene, threads: int = 1, focus: int = 0) -> NDArray[np.bool_]:
    """(H, W) bool: the focus instance's pixels not hidden by clutter or the other instances."""
    W, H = scene.camera.width, scene.camera.height
    img = pv.render(scene_sdl(scene, "label", focus), W, H, antialias=None, threads=threads)
    return (img[..., 0] > 127) & (img[..., 1] < 128)
