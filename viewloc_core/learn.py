"""Learning a view-based object model (paper §3, §4.1; DESIGN.md §2 steps 1-5).

Training views come from either source:

- a mesh, rendered coarse to fine over the view sphere with varied lighting;
- real images with known viewing angles, distance and intrinsics (the paper's
  coffee-machine path), warped into the canonical training camera.

Each training view is then clustered incrementally (Pope & Lowe 2000): it is
aligned to the existing model views that could explain it and joins the one
that lowers the description length (model bits + data bits, MDL) most, or
founds a new model view. Generation stops when a whole subdivision level adds
no model view (§4.1's stopping criterion).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, fields, replace
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
import trimesh
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from viewloc_core import similarity as sim2
from viewloc_core.align import (
    AlignConfig,
    ModelIndex,
    align,
    build_index,
    coverage,
    extend,
    spread_subset,
)
from viewloc_core.camera import Camera
from viewloc_core.contour_job import ContourJob
from viewloc_core.errors import Cancelled, InvalidInputError
from viewloc_core.features import (
    KIND_PARALLEL,
    FeatureConfig,
    ImageFeatures,
    extract_features,
    orientation_bin,
    to_grey_float,
)
from viewloc_core.mesh import MAX_FACES, mesh_vertex_colours, outward_wound
from viewloc_core.model import ModelView, ObjectModel, TrainingViews
from viewloc_core.part_colour import ColourAccumulator
from viewloc_core.pose import Pose, rot_z
from viewloc_core.symmetry import Symmetries
from viewloc_core.view_sphere import direction_from_angles, view_directions, view_rotation

if TYPE_CHECKING:
    from viewloc_core.contour_model import ContourModel

ProgressFn = Callable[[str, float], None]
StopFn = Callable[[], bool]

_LOG = logging.getLogger(__name__)

#: Bits to code one grouped feature from scratch: position (2 x 7 bits at
#: 1 px), orientation (6), scale (5), attributes (2 x 5).
BITS_NEW_FEATURE = 35.0
#: Bits to code one grouped feature as a small residual of a model feature.
BITS_MATCHED_FEATURE = 8.0
#: Bits to code one edge sample from scratch / as explained by the model.
BITS_NEW_EDGE = 18.0
BITS_EXPLAINED_EDGE = 2.0
#: Bits for the similarity that maps a training view into a model view.
BITS_TRANSFORM = 48.0


#: Depth renders (views × mesh faces) the contour views may cost in all:
#: about 12 s with Mesa's software renderer on the 2-core machine (about 1.2
#: µs per face and view). A denser mesh's contour views render its
#: simplification to this budget (:func:`contour_render_mesh`).
CONTOUR_FACE_RENDERS = 10_000_000

#: A training view is rendered over white instead of black when a quarter of
#: its outline is darker than this (grey level, full scale 1) over black. A
#: scene's background is unknown, and against almost any of them the outline
#: is an edge. Over black a dark part's outline is faint: where the part has
#: bright details or texture (a drill's chuck, a scanned mesh's colours),
#: those set the scale of the training view's edge map and the outline ranks
#: with the texture inside. On LM-O the driller's outline has a lower
#: quartile of 0.12 over all views; 0.47 of the edges of its 12 level-0
#: views lay on the outline over black, 0.90 over white, and seeded at the
#: true place in the photos its best view rose from chance (log likelihood
#: ratio -35 to +56) to +46 to +163. Ape, can, cat, barbell, bracket and
#: free-form have no view under the level (their outlines' lower quartiles
#: 0.35-0.53), so their models are unchanged.
DARK_OUTLINE_LEVEL = 0.2
#: Grey level of the training renders' background: black, or white for a
#: dark part (see DARK_OUTLINE_LEVEL).
BLACK_RGB = (0, 0, 0)
WHITE_RGB = (255, 255, 255)


def contour_render_mesh(mesh: trimesh.Trimesh, n_views: int) -> trimesh.Trimesh:
    """The mesh the contour model's ``n_views`` views render to find which of
    ``mesh``'s contour points they see: ``mesh`` itself, or where views ×
    faces would exceed :data:`CONTOUR_FACE_RENDERS` its quadric
    simplification to that budget (:mod:`viewloc_core.mesh_simplify`).

    The points are taken from ``mesh``'s own edges either way; only the
    visibility test and the silhouette's normals read the render. Before,
    a dense mesh got fewer views instead (162 rather than 642 for more than
    15,576 faces), and from 16° apart a curved surface's outline projects
    inside the true one: LM-O, the can (45,666 faces), cat (31,468) and
    driller (25,306) had 162.

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The part, mm.
    n_views : int
        Contour views (at least 1).

    Returns
    -------
    trimesh.Trimesh
    """
    from viewloc_core.mesh_simplify import simplified

    return simplified(mesh, max(4, CONTOUR_FACE_RENDERS // max(1, n_views)))


@dataclass(frozen=True, slots=True)
class LearningConfig:
    """How an object is learned.

    Attributes
    ----------
    max_level : int
        Finest view-sphere subdivision level (0: 12 views ... 3: 642 views).
    min_level : int
        Levels always generated before the stopping criterion applies.
    max_polar_deg : float
        Only views with polar angle <= this (180 = whole sphere, 90 = upper
        hemisphere for parts lying on a table).
    contour_level : int
        View-sphere level of the refinement's contour views (3: 642 views,
        neighbours about 8° apart), independent of where learning stopped.
        The occluding contour of a curved surface moves over it as the view
        turns, so points taken from a view ``θ`` away project inside the true
        outline and pull the fit nearer: at level 2 (about 16° apart) a smooth
        part's fits from the true pose ended a median 1.3 mm (up to 23 mm at
        950 mm) too near on the hard bench set, at level 3 0.3 mm. Each level
        costs four times the depth renders (level 3: about 7 s for a part of
        5,000 faces); a mesh too dense for :data:`CONTOUR_FACE_RENDERS`
        renders its simplification (:func:`contour_render_mesh`).
    object_px : float
        Object diameter in training-image pixels.
    edge_samples : int
        Dense edge samples kept per training view.
    min_presence : float
        Model features seen in fewer than this fraction of a cluster's views
        are dropped once the cluster has ``prune_after`` members.
    prune_after : int
    candidates : int
        Model views a training view is aligned to when clustering.
    join_min_fit : float
        A training view may join a model view only when at least this
        fraction of its edge samples is explained by the model view and of
        the model view's by it. MDL alone favours merging whenever anything
        is shared; this keeps a model view specific enough to verify with.
    seed : int
        Seed of the lighting randomisation; learning is deterministic for it.
    max_faces : int
        A mesh with more faces is learned from its quadric simplification
        to this many (:mod:`viewloc_core.mesh_simplify`). The software
        renderer's cost grows with the faces, and learning renders the mesh
        300-500 times: on the 2-core machine the LM-O ape subdivided to
        747,392 faces (the same shape) took 103 s to learn, simplified to
        100,000 faces first 60 s, to 50,000 46 s; the LM-O driller
        subdivided to 1,619,584 faces 54 s from its PLY's bytes to the model.
        Fewer costs accuracy on real photos: the LM-O parts learned from
        10,000 faces (the can has 45,666) gave AR_MSSD / AR_MSPD 0.151 /
        0.207 against 0.174 / 0.239 (every 4th photo). Every bench part has
        at most 50,000 faces, so none is simplified.
    visual_hull : bool
        Learning from photos with masks also carves the part's visual hull
        (:mod:`viewloc_core.visual_hull`) and learns its outline as the
        contour model, so the part's fits are refined as a mesh's are.
        Without masks (or with fewer than
        :data:`viewloc_core.visual_hull.MIN_HULL_VIEWS`, or photos that
        leave a side unseen, :data:`viewloc_core.visual_hull.MAX_UNSEEN_ANGLE_DEG`)
        there is no hull, and a pose is its nearest training view's.
    """

    max_level: int = 2
    min_level: int = 1
    max_polar_deg: float = 180.0
    contour_level: int = 3
    object_px: float = 128.0
    edge_samples: int = 160
    min_presence: float = 0.25
    prune_after: int = 4
    candidates: int = 4
    join_min_fit: float = 0.7
    seed: int = 0
    max_faces: int = 50_000
    visual_hull: bool = True

    @classmethod
    def from_dict(cls, data: dict[str, Any] | None) -> LearningConfig:
        """Validated configuration from a JSON object (``spec.learning``).

        Raises
        ------
        InvalidInputError
            ``field="learning.<name>"`` for unknown keys or bad values.
        """
        data = dict(data or {})
        known = {f.name: f for f in fields(cls)}
        values: dict[str, Any] = {}
        for key, value in data.items():
            if key not in known:
                raise InvalidInputError(f"unknown learning option {key!r}", f"learning.{key}")
            default = getattr(cls(), key)
            if isinstance(default, bool):
                if not isinstance(value, bool):
                    raise InvalidInputError("must be true or false", f"learning.{key}")
            elif isinstance(default, int):
                if isinstance(value, bool) or not isinstance(value, int):
                    raise InvalidInputError("must be an integer", f"learning.{key}")
            elif isinstance(default, float):
                if isinstance(value, bool) or not isinstance(value, int | float):
                    raise InvalidInputError("must be a number", f"learning.{key}")
                value = float(value)
                if not math.isfinite(value):
                    raise InvalidInputError("must be finite", f"learning.{key}")
            values[key] = value
        config = cls(**values)
        config.validate()
        return config

    def validate(self) -> None:
        """Raise InvalidInputError naming the first out-of-range option."""
        checks = [
            ("max_level", 0 <= self.max_level <= 4, "must be in 0..4"),
            ("min_level", 0 <= self.min_level <= self.max_level, "must be in 0..max_level"),
            ("max_polar_deg", 30.0 <= self.max_polar_deg <= 180.0, "must be in 30..180"),
            ("contour_level", 0 <= self.contour_level <= 4, "must be in 0..4"),
            ("object_px", 48.0 <= self.object_px <= 400.0, "must be in 48..400"),
            ("edge_samples", 32 <= self.edge_samples <= 1000, "must be in 32..1000"),
            ("min_presence", 0.0 <= self.min_presence < 1.0, "must be in [0, 1)"),
            ("prune_after", 2 <= self.prune_after <= 100, "must be in 2..100"),
            ("candidates", 1 <= self.candidates <= 50, "must be in 1..50"),
            ("join_min_fit", 0.0 <= self.join_min_fit <= 1.0, "must be in [0, 1]"),
            ("seed", 0 <= self.seed < 2**32, "must be in 0..2^32-1"),
            ("max_faces", 1_000 <= self.max_faces <= MAX_FACES,
             f"must be in 1000..{MAX_FACES}"),
        ]
        for name, ok, message in checks:
            if not ok:
                raise InvalidInputError(message, f"learning.{name}")
        # The levels and the polar limit are each in range, yet together they
        # can leave no view: learning then failed in its job, not here
        # (level 0 within 30° has none).
        for name, level in (("max_polar_deg", self.max_level),
                            ("contour_level", self.contour_level)):
            if not view_directions(level, self.max_polar_deg):
                raise InvalidInputError(
                    f"view-sphere level {level} has no view within max_polar_deg "
                    f"{self.max_polar_deg:g}; raise the level or the polar limit",
                    f"learning.{name}")


@dataclass(frozen=True, slots=True)
class TrainingView:
    """Known viewpoint of one real training image (API: ``spec.views[i]``).

    Attributes
    ----------
    azimuth_deg, polar_deg : float
        Direction from the object origin to the camera (object frame).
    distance_mm : float
        Distance of the object origin from the camera; the origin is assumed
        on the optical axis.
    inplane_deg : float
        Rotation of the camera about its optical axis relative to the fixed
        up rule of ``view_sphere`` (positive turns the image content clockwise
        on screen, like ``Similarity2D.angle_deg``).
    """

    azimuth_deg: float
    polar_deg: float
    distance_mm: float
    inplane_deg: float = 0.0

    def pose(self) -> Pose:
        """The pose this view states: object to the photo's camera, mm."""
        rotation = view_rotation(direction_from_angles(self.azimuth_deg, self.polar_deg))
        return Pose(rot_z(math.radians(self.inplane_deg)) @ rotation,
                    np.array([0.0, 0.0, self.distance_mm]))


@dataclass(slots=True)
class _Cluster:
    """A model view while it is being learned (mutable)."""

    kind: NDArray[np.int8]
    xy: NDArray[np.float64]
    theta: NDArray[np.float64]
    scale: NDArray[np.float64]
    attrs: NDArray[np.float64]
    count: NDArray[np.float64]
    pos_var: NDArray[np.float64]
    n_members: int
    edge_xy: NDArray[np.float64]
    edge_theta: NDArray[np.float64]
    # Alignment index of the cluster as a one-view model; rebuilt after updates.
    index: tuple[ObjectModel, ModelIndex] | None = None

    def frozen(self) -> ModelView:
        return ModelView(
            self.kind.astype(np.int8), self.xy.astype(np.float32),
            self.theta.astype(np.float32), self.scale.astype(np.float32),
            self.attrs.astype(np.float32), self.count.astype(np.float32),
            self.pos_var.astype(np.float32), self.n_members,
            self.edge_xy.astype(np.float32), self.edge_theta.astype(np.float32),
        )


@dataclass(frozen=True, slots=True)
class _ViewSample:
    """Features of one training view in canonical model-view coordinates."""

    feats: ImageFeatures
    kind: NDArray[np.int8]
    xy: NDArray[np.float64]
    theta: NDArray[np.float64]
    scale: NDArray[np.float64]
    attrs: NDArray[np.float64]
    edge_xy: NDArray[np.float64]
    edge_theta: NDArray[np.float64]


def _contour_directions(config: LearningConfig) -> NDArray[np.float64]:
    """(V, 3) unit directions (object origin to camera) of the contour
    model's views (``config.contour_level``)."""
    return np.array([v.direction for v in view_directions(config.contour_level,
                                                          config.max_polar_deg)])


def contour_of(mesh: trimesh.Trimesh, config: LearningConfig, renderer: Any, d0: float,
               f: float, size: int) -> ContourModel:
    """The refinement's contour model of ``mesh`` (the centred part or a
    hull) from the views of :func:`_contour_directions`, seen through
    :func:`contour_render_mesh`."""
    from viewloc_core.contour_model import build_contour_model

    directions = _contour_directions(config)
    return build_contour_model(mesh, directions, renderer, d0, f, (size, size),
                               visibility_mesh=contour_render_mesh(mesh, len(directions)))


def _canonical_camera(config: LearningConfig, diameter_mm: float) -> tuple[float, float, int]:
    """(d0_mm, f_train_px, size_px) of the canonical training camera."""
    # A distance of a few diameters keeps perspective mild, like the scenes.
    d0 = 4.0 * diameter_mm
    f = config.object_px * d0 / diameter_mm
    size = int(math.ceil(config.object_px * 1.25 / 2.0) * 2)
    return d0, f, size


def _canonical_map(camera: Camera, view: TrainingView, d0_mm: float, f_px: float,
                   size_px: int) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Where each canonical training-camera pixel lies in a real training image.

    The canonical camera (focal ``f_px``, square pixels, no distortion,
    principal point at the centre) sees the object at ``d0_mm`` with the
    photo's in-plane turn undone; the photo's camera sees it at
    ``view.distance_mm`` on its optical axis. Going through the photo
    camera's own projection handles non-square pixels and lens distortion.

    Returns
    -------
    map_x, map_y : (size_px, size_px) float32
        Source pixel coordinates for :func:`cv2.remap`.
    """
    c = (size_px - 1) / 2.0
    v, u = np.mgrid[0:size_px, 0:size_px].astype(np.float64)
    # Canonical pixel -> normalised ray of the photo camera: scale by the
    # distance ratio, then turn by the in-plane angle.
    k = d0_mm / (f_px * view.distance_mm)
    a = math.radians(view.inplane_deg)
    du, dv = (u - c).ravel() * k, (v - c).ravel() * k
    x_n = math.cos(a) * du - math.sin(a) * dv
    y_n = math.sin(a) * du + math.cos(a) * dv
    uv = camera.project(np.column_stack([x_n, y_n, np.ones_like(x_n)]))
    map_x = uv[:, 0].reshape(size_px, size_px).astype(np.float32)
    map_y = uv[:, 1].reshape(size_px, size_px).astype(np.float32)
    return map_x, map_y


def outline_hidden_on_black(image: NDArray[np.generic], mask: NDArray[np.bool_]) -> bool:
    """Whether a render over black hides a quarter of the part's outline.

    Parameters
    ----------
    image : (H, W, 3) uint8
        The part rendered over black.
    mask : (H, W) bool
        The part's pixels.

    Returns
    -------
    bool
        True when the lower quartile of the grey level (as the features see
        it, :func:`to_grey_float`) along the outline is under
        :data:`DARK_OUTLINE_LEVEL`. The outline is taken one pixel inside the
        mask: the outermost pixels are blended with the background.
    """
    inner = cv2.erode(mask.astype(np.uint8), np.ones((3, 3), np.uint8))
    outline = (inner > 0) & (cv2.erode(inner, np.ones((3, 3), np.uint8)) == 0)
    if not outline.any():
        return False
    grey = to_grey_float(image)[outline]
    return bool(np.percentile(grey, 25.0) < DARK_OUTLINE_LEVEL)


def _sample_from_image(
    image: NDArray[np.generic], mask: NDArray[np.bool_] | None, centre: float,
    config: LearningConfig, rng: np.random.Generator,
) -> _ViewSample:
    feats = extract_features(image, FeatureConfig(), mask=mask)
    g = feats.grouped
    offset = np.array([centre, centre])
    pick = spread_subset(feats.edge_xy.astype(np.float64), config.edge_samples, rng)
    return _ViewSample(
        feats,
        g.kind,
        g.xy.astype(np.float64) - offset,
        g.theta.astype(np.float64),
        g.scale.astype(np.float64),
        g.attrs.astype(np.float64),
        feats.edge_xy[pick].astype(np.float64) - offset,
        feats.edge_theta[pick].astype(np.float64),
    )


def _new_cluster(sample: _ViewSample) -> _Cluster:
    n = len(sample.kind)
    return _Cluster(
        sample.kind.copy(), sample.xy.copy(), sample.theta.copy(), sample.scale.copy(),
        sample.attrs.copy(), np.ones(n), np.full(n, 2.0), 1,
        sample.edge_xy.copy(), sample.edge_theta.copy(),
    )


def _pair_features(
    cluster: _Cluster, sample: _ViewSample, sim_t2m: NDArray[np.float64], gate_px: float = 4.0
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.float64]]:
    """Pair cluster features with sample features under a similarity.

    Returns cluster indices, sample indices and the sample positions mapped
    into the cluster frame.
    """
    if len(cluster.kind) == 0 or len(sample.kind) == 0:
        e = np.zeros(0, np.int64)
        return e, e, np.zeros((0, 2))
    mapped = sim2.apply(sim_t2m, sample.xy)
    tree = cKDTree(mapped)
    dist, nn = tree.query(cluster.xy, k=1, distance_upper_bound=gate_px)
    ci, si = [], []
    taken: set[int] = set()
    for c in np.argsort(dist):
        if not np.isfinite(dist[c]):
            break
        s = int(nn[c])
        if s in taken or sample.kind[s] != cluster.kind[c]:
            continue
        period = np.pi if cluster.kind[c] == KIND_PARALLEL else 2 * np.pi
        dth = np.mod(sample.theta[s] + sim_t2m[2] - cluster.theta[c] + period / 2, period)
        if abs(dth - period / 2) > np.radians(20.0):
            continue
        taken.add(s)
        ci.append(int(c))
        si.append(s)
    ci_a, si_a = np.array(ci, np.int64), np.array(si, np.int64)
    return ci_a, si_a, mapped[si_a] if len(si_a) else np.zeros((0, 2))


def _edges_explained(cluster: _Cluster, sample: _ViewSample,
                     sim_t2m: NDArray[np.float64]) -> int:
    """How many of the sample's edge samples the cluster's edges explain."""
    if len(cluster.edge_xy) == 0 or len(sample.edge_xy) == 0:
        return 0
    mapped = sim2.apply(sim_t2m, sample.edge_xy)
    dist, nn = cKDTree(cluster.edge_xy).query(mapped, k=1, distance_upper_bound=2.5)
    ok = np.isfinite(dist)
    dth = np.abs(np.mod(sample.edge_theta[ok] + sim_t2m[2] - cluster.edge_theta[nn[ok]], np.pi))
    dth = np.minimum(dth, np.pi - dth)
    return int(np.count_nonzero(dth < np.radians(20.0)))


def _description_length_new(sample: _ViewSample) -> float:
    """Bits to add a training view as a new model view."""
    return len(sample.kind) * BITS_NEW_FEATURE + len(sample.edge_xy) * BITS_NEW_EDGE


def _description_length_join(
    cluster: _Cluster, sample: _ViewSample, n_matched: int, n_explained: int
) -> float:
    """Bits to code a training view with a model view (plus the model's growth)."""
    p = (cluster.count + 0.5) / (cluster.n_members + 1.0)
    unmatched_model = max(len(cluster.kind) - n_matched, 0)
    # Model features the view lacks cost -log2(1 - p) each (on average).
    missing_bits = unmatched_model * float(np.mean(-np.log2(np.maximum(1 - p, 1e-3)))) if len(
        p) else 0.0
    return (
        BITS_TRANSFORM
        + n_matched * BITS_MATCHED_FEATURE
        + (len(sample.kind) - n_matched) * BITS_NEW_FEATURE
        + n_explained * BITS_EXPLAINED_EDGE
        + (len(sample.edge_xy) - n_explained) * BITS_NEW_EDGE
        + missing_bits
    )


def _align_to_cluster(
    cluster: _Cluster, sample: _ViewSample, config: AlignConfig
) -> NDArray[np.float64] | None:
    """Similarity cluster frame -> sample image pixels, or None if they do not align."""
    if cluster.index is None:
        model = _single_view_model(cluster)
        cluster.index = (model, build_index(model))
    model, index = cluster.index
    matches = align(model, index, sample.feats, config, max_matches=1)
    return matches[0].sim.copy() if matches else None


def _single_view_model(cluster: _Cluster) -> ObjectModel:
    mv = cluster.frozen()
    training = TrainingViews(
        np.eye(3)[None], np.zeros(1), np.zeros(1), np.zeros(1, np.int64),
        np.array([[0.0, 0.0, 0.0, 1.0]]), [mv.edge_xy], [mv.edge_theta],
    )
    radius = float(np.max(np.linalg.norm(cluster.edge_xy, axis=1))) if len(
        cluster.edge_xy) else 50.0
    return ObjectModel("mesh", 2.0 * radius, 1.0, 1.0, 0, np.zeros(3), [mv], training)


def _update_cluster(cluster: _Cluster, sample: _ViewSample, sim_t2m: NDArray[np.float64],
                    config: LearningConfig) -> None:
    ci, si, mapped = _pair_features(cluster, sample, sim_t2m)
    n = cluster.n_members
    cluster.index = None
    if len(ci):
        w_old = cluster.count[ci]
        new_count = w_old + 1.0
        delta = mapped - cluster.xy[ci]
        cluster.xy[ci] += delta / new_count[:, None]
        # Running variance (isotropic), floored so one view cannot make it 0.
        sq = (delta**2).sum(axis=1) / 2.0
        cluster.pos_var[ci] = np.maximum(
            (cluster.pos_var[ci] * w_old + sq * w_old / new_count) / new_count, 1.0
        )
        period = np.where(cluster.kind[ci] == KIND_PARALLEL, np.pi, 2 * np.pi)
        dth = np.mod(sample.theta[si] + sim_t2m[2] - cluster.theta[ci] + period / 2, period)
        cluster.theta[ci] = np.mod(cluster.theta[ci] + (dth - period / 2) / new_count, period)
        cluster.scale[ci] += (sample.scale[si] * sim_t2m[3] - cluster.scale[ci]) / new_count
        cluster.attrs[ci] += (sample.attrs[si] - cluster.attrs[ci]) / new_count[:, None]
        cluster.count[ci] = new_count
    unmatched = np.setdiff1d(np.arange(len(sample.kind)), si)
    if len(unmatched):
        cluster.kind = np.concatenate([cluster.kind, sample.kind[unmatched]])
        cluster.xy = np.concatenate([cluster.xy, sim2.apply(sim_t2m, sample.xy[unmatched])])
        period = np.where(sample.kind[unmatched] == KIND_PARALLEL, np.pi, 2 * np.pi)
        cluster.theta = np.concatenate(
            [cluster.theta, np.mod(sample.theta[unmatched] + sim_t2m[2], period)]
        )
        cluster.scale = np.concatenate([cluster.scale, sample.scale[unmatched] * sim_t2m[3]])
        cluster.attrs = np.concatenate([cluster.attrs, sample.attrs[unmatched]])
        cluster.count = np.concatenate([cluster.count, np.ones(len(unmatched))])
        cluster.pos_var = np.concatenate([cluster.pos_var, np.full(len(unmatched), 2.0)])
    cluster.n_members = n + 1
    if cluster.n_members >= config.prune_after:
        keep = (cluster.count / cluster.n_members) >= config.min_presence
        for name in ("kind", "xy", "theta", "scale", "attrs", "count", "pos_var"):
            setattr(cluster, name, getattr(cluster, name)[keep])


class _Clusterer:
    """Incremental conceptual clustering of training views into model views."""

    def __init__(self, config: LearningConfig, centre_px: float) -> None:
        self.config = config
        # Training images are square; their centre is the model-view origin.
        self._centre = centre_px
        self.align_config = AlignConfig(
            min_scale=0.8, max_scale=1.25, max_extended=60, icp_radii_px=(6.0, 3.0, 1.5),
        )
        self.clusters: list[_Cluster] = []
        self.member_of: list[int] = []
        self.sim_to_model: list[NDArray[np.float64]] = []
        self.directions: list[NDArray[np.float64]] = []

    def add(self, sample: _ViewSample, direction: NDArray[np.float64]) -> None:
        best: tuple[float, int, NDArray[np.float64]] | None = None
        dl_new = _description_length_new(sample)
        for c in self._candidates(direction):
            cluster = self.clusters[c]
            sim_m2img = self._align(cluster, sample)
            if sim_m2img is None:
                continue
            # align() reports cluster frame -> sample image pixels; the sample's
            # own frame is centred, so undo the centring before inverting.
            sim_m2t = sim_m2img.copy()
            sim_m2t[:2] -= self._centre
            sim_t2m = sim2.inverse(sim_m2t)
            ci, _, _ = _pair_features(cluster, sample, sim_t2m)
            explained = _edges_explained(cluster, sample, sim_t2m)
            fit_sample = explained / max(len(sample.edge_xy), 1)
            fit_model = coverage(
                sample.feats, sim_m2img, cluster.edge_xy, orientation_bin(cluster.edge_theta)
            )
            if min(fit_sample, fit_model) < self.config.join_min_fit:
                continue
            dl = _description_length_join(cluster, sample, len(ci), explained)
            if dl < dl_new and (best is None or dl < best[0]):
                best = (dl, c, sim_t2m)
        if best is None:
            self.clusters.append(_new_cluster(sample))
            self.member_of.append(len(self.clusters) - 1)
            self.sim_to_model.append(np.array([0.0, 0.0, 0.0, 1.0]))
        else:
            _, c, sim_t2m = best
            _update_cluster(self.clusters[c], sample, sim_t2m, self.config)
            self.member_of.append(c)
            self.sim_to_model.append(sim_t2m)
        self.directions.append(direction)

    def _align(self, cluster: _Cluster, sample: _ViewSample) -> NDArray[np.float64] | None:
        """Similarity cluster frame -> sample image pixels, or None.

        Neighbouring views usually differ by little more than the identity,
        so that is tried first (one extension); the full probabilistic
        alignment runs only when it does not fit (symmetric or rotated views).
        """
        start = np.array([self._centre, self._centre, 0.0, 1.0])
        theta = cluster.edge_theta
        fitted = extend(sample.feats, start, cluster.edge_xy, theta, self.align_config)
        bins = orientation_bin(theta)
        if coverage(sample.feats, fitted, cluster.edge_xy, bins) >= self.config.join_min_fit:
            return fitted
        return _align_to_cluster(cluster, sample, self.align_config)

    def _candidates(self, direction: NDArray[np.float64]) -> list[int]:
        """Model views to try: those whose members look from the nearest directions."""
        if not self.clusters:
            return []
        dirs = np.array(self.directions)
        cos = dirs @ direction
        order = np.argsort(-cos)
        seen: list[int] = []
        for t in order:
            c = self.member_of[t]
            if c not in seen:
                seen.append(c)
            if len(seen) >= self.config.candidates:
                break
        return seen


def _check_should_stop(should_stop: StopFn | None) -> None:
    if should_stop is not None and should_stop():
        raise Cancelled("learning was cancelled")


def _finish(
    clusterer: _Clusterer, rotations: Sequence[NDArray[np.float64]],
    samples: Sequence[_ViewSample], angles: Sequence[tuple[float, float]],
    source: str, diameter_mm: float, d0: float, f: float, size: int,
    origin_offset: NDArray[np.float64], config: LearningConfig,
    mesh: trimesh.Trimesh | None,
) -> ObjectModel:
    training = TrainingViews(
        np.array(rotations),
        np.array([a for a, _ in angles]),
        np.array([p for _, p in angles]),
        np.array(clusterer.member_of, np.int64),
        np.array(clusterer.sim_to_model),
        [s.edge_xy.astype(np.float32) for s in samples],
        [s.edge_theta.astype(np.float32) for s in samples],
    )
    return ObjectModel(
        source=source,
        diameter_mm=diameter_mm,
        d0_mm=d0,
        f_train_px=f,
        train_size_px=size,
        origin_offset_mm=origin_offset,
        model_views=[c.frozen() for c in clusterer.clusters],
        training=training,
        mesh_vertices_mm=None if mesh is None else np.asarray(mesh.vertices, np.float32),
        mesh_faces=None if mesh is None else np.asarray(mesh.faces, np.int32),
        mesh_vertex_colours=None if mesh is None else mesh_vertex_colours(mesh),
        config=asdict(config),
    )


def learn_from_mesh(
    mesh: trimesh.Trimesh,
    config: LearningConfig = LearningConfig(),
    progress: ProgressFn | None = None,
    rng: np.random.Generator | int | None = None,
    should_stop: StopFn | None = None,
    symmetries: Symmetries | None = None,
) -> ObjectModel:
    """Learn a view-based model of a mesh (paper §4.1).

    Parameters
    ----------
    mesh : trimesh.Trimesh
        The part, in mm (``mesh.load_mesh`` converts). One of more than
        ``config.max_faces`` faces is learned from its simplification
        (:func:`viewloc_core.mesh_simplify.simplified`), in the same frame.
    config : LearningConfig
    progress : callable, optional
        ``progress(stage, fraction)``; stage like ``"rendering view 12 of 162"``.
    rng : Generator, int or None
        Seed for the lighting; None uses ``config.seed``.
    should_stop : callable, optional
        Polled between views; True raises ``Cancelled``.
    symmetries : Symmetries, optional
        The part's symmetry group in the mesh's frame (mm), e.g. from
        :func:`viewloc_core.symmetry.declared_symmetries`; stored as given
        instead of the one :func:`viewloc_core.symmetry.detect_symmetries`
        finds (which runs only when this is None).

    Returns
    -------
    ObjectModel
    """
    from viewloc_core.crease_visibility import confirmed_shares, creases_show
    from viewloc_core.mesh import mesh_diameter_mm
    from viewloc_core.mesh_simplify import simplified
    from viewloc_core.render import Renderer, prepare, random_lights
    from viewloc_core.symmetry import detect_symmetries

    config.validate()
    gen = np.random.default_rng(config.seed if rng is None else rng)
    # The frame and size are the uploaded mesh's own, to the last digit,
    # whatever the simplification moves.
    centre = np.asarray(mesh.bounds, np.float64).mean(axis=0)
    diameter = mesh_diameter_mm(mesh)
    if progress is not None and len(mesh.faces) > config.max_faces:
        progress(f"simplifying the mesh to {config.max_faces} faces", 0.0)
    part = simplified(outward_wound(mesh), config.max_faces)
    centred = part.copy()
    centred.apply_translation(-centre)
    d0, f, size = _canonical_camera(config, diameter)
    c = (size - 1) / 2.0
    camera = Camera(f, f, c, c, size, size)
    directions = view_directions(config.max_level, config.max_polar_deg)
    total = len(directions)
    clusterer = _Clusterer(config, c)
    rotations: list[NDArray[np.float64]] = []
    samples: list[_ViewSample] = []
    angles: list[tuple[float, float]] = []
    views_seen: list[NDArray[np.uint8]] = []
    # The contour model needs none of the training views: a child process
    # builds it meanwhile (contour_job), stopped if learning stops.
    with Renderer() as renderer, ContourJob(centred, config, d0, f, size) as contour_job:
        # The training views render the part's own faces. Rendering them
        # from a simplification to 10,000 faces (a 160-px view shows little
        # more; the LM-O can's colour render 127 -> 27 ms) learned 7-30 %
        # faster (hole puncher 52 -> 42 s, two benches at once) but lost AR
        # on real photos: LM-O objects 9-12, AR_MSSD / AR_MSPD 0.191 / 0.273
        # -> 0.184 / 0.266 at learning seed 0, 0.198 / 0.276 -> 0.184 / 0.263
        # at seed 1 (the hole puncher lost most: 0.234 -> 0.212 and 0.248
        # -> 0.212). The renderer keeps only 1.1-1.3 cores busy; clustering
        # each view on a second thread while the next one rendered learned
        # the LM-O can, egg box and hole puncher in 41 s instead of 48-50 s,
        # to the same model, but crashed the process now and then (1 of 176
        # fresh processes learning the bracket, and one CI run, with OpenCV
        # running beside the render): the views are done one after another
        # here.
        prepared = prepare(centred)
        # Only a mesh with colours of its own says what colour the part is.
        colours = (ColourAccumulator(config.seed)
                   if prepared.colours_linear is not None or prepared.texture is not None
                   else None)
        level_counts: dict[int, int] = {}
        for i, view in enumerate(directions):
            if view.level > config.min_level and view.level not in level_counts:
                # A new level starts: stop when the previous one added nothing.
                prev = level_counts.get(view.level - 1)
                before = level_counts.get(view.level - 2)
                if prev is not None and before is not None and prev <= before:
                    break
            _check_should_stop(should_stop)
            if progress is not None:
                progress(f"rendering view {i + 1} of {total}", i / total)
            R = view.R_m2c
            pose = Pose(R, np.array([0.0, 0.0, d0]))
            lights = random_lights(gen)
            result = renderer.render(prepared, camera, pose, lights=lights,
                                     background_rgb=BLACK_RGB)
            seen = result.color
            if outline_hidden_on_black(result.color, result.mask):
                # The same view and lights over white: the colour histogram
                # still takes the render over black (its mask's edge pixels
                # are blended with the background).
                seen = renderer.render(prepared, camera, pose, lights=lights,
                                       background_rgb=WHITE_RGB).color
            sample = _sample_from_image(seen, result.mask, c, config, gen)
            views_seen.append(seen)
            if colours is not None:
                colours.add(result.color, result.mask)
            clusterer.add(sample, view.direction)
            rotations.append(R)
            samples.append(sample)
            angles.append((view.azimuth_deg, view.polar_deg))
            level_counts[view.level] = len(clusterer.clusters)
        if progress is not None:
            progress("building contour model", 0.99)
        # 3D contour points per direction of a finer sphere than training
        # needs (see contour_level), in the centred frame the poses are
        # computed in, for the pose refinement (§5.2).
        contour = contour_job.result()
        if contour is None:
            _LOG.warning("contour model built after the training views: %s",
                         contour_job.failure)
            contour = contour_of(centred, config, renderer, d0, f, size)
        # A part whose own views do not show its creases (a dark part) is
        # fitted and scored by its outline alone (crease_visibility).
        if not creases_show(*confirmed_shares(contour, views_seen, rotations, camera, d0)):
            contour = contour.outline_only()
    if progress is not None:
        progress("finishing", 1.0)
    model = _finish(clusterer, rotations, samples, angles, "mesh", diameter, d0, f, size,
                    centre, config, part)
    sym = detect_symmetries(part, rng=0) if symmetries is None else symmetries
    histogram = None if colours is None else colours.histogram()
    return with_symmetries(replace(model, contour=contour.to_arrays(),
                                   colour_histogram=histogram), sym)


def with_symmetries(model: ObjectModel, sym: Symmetries) -> ObjectModel:
    """``model`` with its symmetry group replaced by ``sym`` (object frame, mm).

    Parameters
    ----------
    model : ObjectModel
    sym : Symmetries
        Discrete transforms (identity first) and the continuous axis, if any.

    Returns
    -------
    ObjectModel
        A copy; ``symmetries`` (K, 4, 4) and ``symmetry_axis`` (6,) or None.
    """
    axis = None
    if sym.continuous_axis is not None and sym.continuous_offset is not None:
        axis = np.concatenate([sym.continuous_axis, sym.continuous_offset])
    return replace(model, symmetries=np.array(sym.discrete, np.float64), symmetry_axis=axis)


def learn_from_images(
    images: Sequence[NDArray[np.generic]],
    masks: Sequence[NDArray[np.generic] | None] | None,
    camera: Camera,
    views: Sequence[TrainingView],
    diameter_mm: float,
    config: LearningConfig = LearningConfig(),
    progress: ProgressFn | None = None,
    rng: np.random.Generator | int | None = None,
    should_stop: StopFn | None = None,
) -> ObjectModel:
    """Learn from real images with known viewpoints (the paper's real-image path).

    Each image is resampled into the canonical training camera (scale from its
    distance and focal lengths, in-plane rotation undone, non-square pixels
    and lens distortion removed through the camera's own projection), so both
    sources give identical model views.

    Parameters
    ----------
    images : sequence of (H, W) or (H, W, 3) arrays
    masks : sequence of (H, W) arrays or None, optional
        Non-zero = object; same order as ``images``.
    camera : Camera
        Intrinsics of the training images.
    views : sequence of TrainingView
        One per image.
    diameter_mm : float
        Object diameter.
    config, progress, rng, should_stop
        As for ``learn_from_mesh``.

    Returns
    -------
    ObjectModel
    """
    config.validate()
    if len(images) == 0:
        raise InvalidInputError("at least one image is needed", "images")
    if len(views) != len(images):
        raise InvalidInputError(
            f"{len(views)} views for {len(images)} images", "spec.views"
        )
    if masks is not None and len(masks) != len(images):
        raise InvalidInputError(f"{len(masks)} masks for {len(images)} images", "masks")
    if not (math.isfinite(diameter_mm) and diameter_mm > 0):
        raise InvalidInputError("must be a positive number", "spec.object_diameter_mm")
    gen = np.random.default_rng(config.seed if rng is None else rng)
    d0, f, size = _canonical_camera(config, diameter_mm)
    c = (size - 1) / 2.0
    clusterer = _Clusterer(config, c)
    colours = ColourAccumulator(config.seed)
    rotations, samples, angles = [], [], []
    # Per photo, its pose (object to photo camera), for the visual hull.
    photo_poses: list[Pose] = []
    for i, (image, view) in enumerate(zip(images, views, strict=True)):
        _check_should_stop(should_stop)
        if progress is not None:
            progress(f"image {i + 1} of {len(images)}", i / len(images))
        if not (math.isfinite(view.distance_mm) and view.distance_mm > 0):
            raise InvalidInputError("must be a positive number", f"spec.views[{i}].distance_mm")
        img = np.asarray(image)
        if img.shape[0] != camera.height or img.shape[1] != camera.width:
            raise InvalidInputError(
                f"image is {img.shape[1]}x{img.shape[0]}, camera says "
                f"{camera.width}x{camera.height}", f"images[{i}]",
            )
        map_x, map_y = _canonical_map(camera, view, d0, f, size)
        warped = cv2.remap(img, map_x, map_y, cv2.INTER_LINEAR)
        mask_w = None
        if masks is not None and masks[i] is not None:
            m = np.asarray(masks[i])
            if m.shape[:2] != img.shape[:2]:
                raise InvalidInputError("mask size differs from its image", f"masks[{i}]")
            mask_w = cv2.remap((m > 0).astype(np.uint8), map_x, map_y, cv2.INTER_NEAREST) > 0
            # Only masked photos say which pixels are the part's colours.
            colours.add(warped, mask_w)
        sample = _sample_from_image(warped, mask_w, c, config, gen)
        direction = direction_from_angles(view.azimuth_deg, view.polar_deg)
        clusterer.add(sample, direction)
        rotations.append(view_rotation(direction))
        samples.append(sample)
        angles.append((view.azimuth_deg, view.polar_deg))
        photo_poses.append(view.pose())
    hull = None
    if config.visual_hull and masks is not None:
        from viewloc_core.visual_hull import visual_hull

        _check_should_stop(should_stop)
        if progress is not None:
            progress("carving the visual hull", 0.95)
        hull = visual_hull(masks, photo_poses, camera, diameter_mm)
    contour = None
    if hull is not None:
        from viewloc_core.render import Renderer

        _check_should_stop(should_stop)
        if progress is not None:
            progress("building contour model", 0.97)
        # The hull's outline is the photos' own; its creases are where the
        # cones meet, not the part's, so only the outline is fitted.
        with Renderer() as renderer:
            contour = contour_of(hull, config, renderer, d0, f, size).outline_only().to_arrays()
    if progress is not None:
        progress("finishing", 1.0)
    model = _finish(clusterer, rotations, samples, angles, "images", diameter_mm, d0, f, size,
                    np.zeros(3), config, hull)
    return replace(model, colour_histogram=colours.histogram(), contour=contour)
