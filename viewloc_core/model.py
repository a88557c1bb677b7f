"""The learned view-based object model (DESIGN.md §2 step 4) and its array form.

An ``ObjectModel`` is a set of *model views*, each a generalised cluster of
training views (Pope & Lowe 2000): per feature a presence probability, a mean
position and variance in the model view's frame, and its attributes; plus
dense oriented edge samples used for verification. Every training view keeps
its viewing rotation, the model view it joined and the similarity that maps it
into that model view, so a detection can report the finest viewing angles.

Model-view coordinates are pixels of the canonical training camera relative
to the projection of the object origin (focal ``f_train_px``, object origin on
the optical axis at ``d0_mm``).

The model is stored as plain arrays plus JSON metadata with a schema version
(``model_to_arrays`` / ``model_from_arrays``); the model store writes them.
"""

from __future__ import annotations

import json
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from viewloc_core.errors import ModelFormatError
from viewloc_core.part_colour import N_BINS
from viewloc_core.symmetry import Symmetries

SCHEMA_VERSION = 1

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class ModelView:
    """One model view: a cluster of similar training views.

    Attributes
    ----------
    kind : (F,) int8
        Feature kind (``features.KIND_*``).
    xy : (F, 2) float32
        Mean feature position, model-view pixels.
    theta : (F,) float32
        Mean orientation, radians.
    scale : (F,) float32
        Mean size, pixels.
    attrs : (F, 2) float32
        Mean attributes.
    count : (F,) float32
        Number of member training views in which the feature was seen.
    pos_var : (F,) float32
        Isotropic position variance, px².
    n_members : int
        Number of training views in the cluster.
    edge_xy : (P, 2) float32
        Oriented edge samples, model-view pixels.
    edge_theta : (P,) float32
        Their orientation modulo π, radians.
    """

    kind: NDArray[np.int8]
    xy: F32
    theta: F32
    scale: F32
    attrs: F32
    count: F32
    pos_var: F32
    n_members: int
    edge_xy: F32
    edge_theta: F32

    @property
    def presence(self) -> F32:
        """(F,) presence probability p_j of each feature (Laplace-smoothed)."""
        return ((self.count + 0.5) / (self.n_members + 1.0)).astype(np.float32)


@dataclass(frozen=True, slots=True)
class TrainingViews:
    """The training views a model was learned from.

    Attributes
    ----------
    R_m2c : (T, 3, 3) float64
        Object -> training camera rotation of each view.
    azimuth_deg, polar_deg : (T,) float64
        Viewing angles (paper §4.2).
    model_view : (T,) int64
        Model view each training view joined.
    sim_to_model : (T, 4) float64
        Similarity ``(x, y, angle_rad, scale)`` mapping the training view's
        pixels into its model view's frame.
    edge_xy : list of (P_t, 2) float32
        Edge samples of each training view, its own frame.
    edge_theta : list of (P_t,) float32
    """

    R_m2c: F64
    azimuth_deg: F64
    polar_deg: F64
    model_view: NDArray[np.int64]
    sim_to_model: F64
    edge_xy: list[F32]
    edge_theta: list[F32]

    def __len__(self) -> int:
        return int(self.R_m2c.shape[0])


@dataclass(frozen=True, slots=True, weakref_slot=True, eq=False)
class ObjectModel:
    """A learned object.

    Attributes
    ----------
    source : str
        ``"mesh"`` or ``"images"``.
    diameter_mm : float
        Largest distance between two object points.
    d0_mm : float
        Distance of the object origin from the training camera.
    f_train_px : float
        Focal length of the canonical training camera.
    train_size_px : int
        Side of the square training images.
    origin_offset_mm : (3,) float64
        Point of the user's object frame used as origin while learning (the
        bounding-box centre); poses are reported in the user's frame.
    model_views : list of ModelView
    training : TrainingViews
    mesh_vertices_mm : (N, 3) float32 or None
        Mesh in the user's object frame, mm (for refinement and overlays).
    mesh_faces : (F, 3) int32 or None
    contour : dict of arrays or None
        Pose refinement's contour model in array form (``contour_model``).
    symmetries : (K, 4, 4) float64
        Discrete object-frame symmetry transforms, the identity first (BOP's
        ``symmetries_discrete``; for a part with a continuous axis: the
        identity and, when present, a 180° flip perpendicular to it).
    symmetry_axis : (6,) float64 or None
        Continuous rotational symmetry: unit axis (3,) then a point on it
        (3,), mm, user's object frame; None when there is none.
    colour_histogram : (part_colour.N_BINS,) float32 or None
        The part's chromaticity histogram over its training views
        (:mod:`viewloc_core.part_colour`); None when the part showed no
        colours of its own (a mesh without colours, grey training images).
    mesh_vertex_colours : (N, 3) uint8 or None
        sRGB colour of each mesh vertex when the uploaded mesh had colours of
        its own (vertex or face colours, a texture); None otherwise. The
        ranking's shading cue reads the part's own pattern from them
        (:mod:`viewloc_core.shading`).
    default_min_score : float
        Detections below this score are not reported unless asked. The score
        is the share of the contour that image edges confirm; in clutter 6D
        fits reach 0.4-0.66 by chance (paper-set object-free images) while
        right ones rarely fall below 0.75, so 0.6 keeps nearly every right
        detection and drops most chance fits (like HALCON's MinScore).
    config : dict
        The learning configuration used, JSON-able.
    """

    source: str
    diameter_mm: float
    d0_mm: float
    f_train_px: float
    train_size_px: int
    origin_offset_mm: F64
    model_views: list[ModelView]
    training: TrainingViews
    mesh_vertices_mm: F32 | None = None
    mesh_faces: NDArray[np.int32] | None = None
    contour: dict[str, Any] | None = None
    symmetries: F64 = field(default_factory=lambda: np.eye(4)[None])
    default_min_score: float = 0.6
    config: dict[str, Any] = field(default_factory=dict)
    symmetry_axis: F64 | None = None
    colour_histogram: F32 | None = None
    mesh_vertex_colours: NDArray[np.uint8] | None = None

    def symmetry_group(self) -> Symmetries:
        """The part's symmetries as :class:`viewloc_core.symmetry.Symmetries`,
        built once per model: a localization asks for them in every fit, and
        checking the group anew (its identity, its axis) cost about 80 µs a
        time."""
        return cached_per_model(_SYMMETRY_GROUPS, self, _symmetry_group)

    @property
    def training_views(self) -> int:
        """Number of training views."""
        return len(self.training)

    @property
    def n_model_views(self) -> int:
        """Number of model views."""
        return len(self.model_views)


_VIEW_FIELDS = ("kind", "xy", "theta", "scale", "attrs", "count", "pos_var")


def _concat(parts: list[NDArray[Any]], empty_shape: tuple[int, ...], dtype: Any) -> NDArray[Any]:
    return np.concatenate(parts) if parts else np.zeros(empty_shape, dtype)


def model_to_arrays(model: ObjectModel) -> tuple[dict[str, NDArray[Any]], dict[str, Any]]:
    """Flatten a model into named arrays and JSON-able metadata.

    Returns
    -------
    arrays : dict of str to ndarray
        Numeric content (ragged lists are concatenated with offset arrays).
    meta : dict
        Scalars, configuration and ``schema_version``.
    """
    mv = model.model_views
    arrays: dict[str, NDArray[Any]] = {}
    for name in _VIEW_FIELDS:
        arrays[f"mv_{name}"] = np.concatenate([getattr(v, name) for v in mv])
    arrays["mv_feat_offsets"] = np.cumsum([0] + [len(v.kind) for v in mv]).astype(np.int64)
    arrays["mv_n_members"] = np.array([v.n_members for v in mv], np.int64)
    arrays["mv_edge_xy"] = np.concatenate([v.edge_xy for v in mv])
    arrays["mv_edge_theta"] = np.concatenate([v.edge_theta for v in mv])
    arrays["mv_edge_offsets"] = np.cumsum([0] + [len(v.edge_theta) for v in mv]).astype(np.int64)
    tr = model.training
    arrays["tv_R_m2c"] = tr.R_m2c
    arrays["tv_azimuth_deg"] = tr.azimuth_deg
    arrays["tv_polar_deg"] = tr.polar_deg
    arrays["tv_model_view"] = tr.model_view
    arrays["tv_sim_to_model"] = tr.sim_to_model
    arrays["tv_edge_xy"] = _concat(tr.edge_xy, (0, 2), np.float32)
    arrays["tv_edge_theta"] = _concat(tr.edge_theta, (0,), np.float32)
    arrays["tv_edge_offsets"] = np.cumsum([0] + [len(e) for e in tr.edge_theta]).astype(np.int64)
    arrays["origin_offset_mm"] = model.origin_offset_mm
    arrays["symmetries"] = model.symmetries
    if model.symmetry_axis is not None:
        arrays["symmetry_axis"] = np.asarray(model.symmetry_axis, np.float64)
    if model.colour_histogram is not None:
        arrays["colour_histogram"] = np.asarray(model.colour_histogram, np.float32)
    if model.mesh_vertices_mm is not None and model.mesh_faces is not None:
        arrays["mesh_vertices_mm"] = model.mesh_vertices_mm
        arrays["mesh_faces"] = model.mesh_faces
        if model.mesh_vertex_colours is not None:
            arrays["mesh_vertex_colours"] = np.asarray(model.mesh_vertex_colours, np.uint8)
    contour_keys: list[str] = []
    contour_meta: dict[str, Any] = {}
    if model.contour is not None:
        for key, value in model.contour.items():
            if isinstance(value, np.ndarray):
                arrays[f"contour_{key}"] = value
                contour_keys.append(key)
            else:
                contour_meta[key] = value
    meta = {
        "schema_version": SCHEMA_VERSION,
        "source": model.source,
        "diameter_mm": model.diameter_mm,
        "d0_mm": model.d0_mm,
        "f_train_px": model.f_train_px,
        "train_size_px": model.train_size_px,
        "default_min_score": model.default_min_score,
        "config": model.config,
        "contour_keys": contour_keys,
        "contour_meta": contour_meta,
        "has_contour": model.contour is not None,
    }
    # Fail here, not at load time, if something is not JSON-able.
    json.dumps(meta)
    return arrays, meta


def _split(flat: NDArray[Any], offsets: NDArray[np.int64]) -> list[NDArray[Any]]:
    return [flat[offsets[i]: offsets[i + 1]] for i in range(len(offsets) - 1)]


def _colour_histogram(arrays: dict[str, NDArray[Any]]) -> F32 | None:
    """The stored colour histogram, checked; None when the model has none."""
    if "colour_histogram" not in arrays:
        return None
    hist = np.asarray(arrays["colour_histogram"], np.float32)
    if hist.shape != (N_BINS,) or not np.all(np.isfinite(hist)):
        raise ValueError(f"colour_histogram must be {N_BINS} finite numbers")
    return hist


def _mesh_vertex_colours(arrays: dict[str, NDArray[Any]]) -> NDArray[np.uint8] | None:
    """The stored vertex colours, checked against the stored vertices; None
    when the model has none."""
    if "mesh_vertex_colours" not in arrays:
        return None
    colours = np.asarray(arrays["mesh_vertex_colours"])
    vertices = arrays.get("mesh_vertices_mm")
    if (colours.dtype != np.uint8 or vertices is None
            or colours.shape != (len(vertices), 3)):
        raise ValueError("mesh_vertex_colours must be one uint8 RGB triple per mesh vertex")
    return colours


#: The numbers of the model's metadata a localization computes with.
_META_NUMBERS = ("diameter_mm", "d0_mm", "f_train_px", "default_min_score")


def _require_finite(arrays: dict[str, NDArray[Any]], meta: dict[str, Any]) -> None:
    """ModelFormatError naming the first float array or metadata number that
    is not finite.

    A checksum shows that the files are as written, not that what was written
    is usable: a model stored before uploads far from the origin were refused
    can hold mesh vertices that overflowed float32 to inf, and every
    localization of it failed inside the core (a 500). Every float array is
    checked, not only the vertices: each is read by some step of a
    localization. Once per load (the store caches models): about 1 ms for a
    3 MB model.
    """
    for name, stored in arrays.items():
        values = np.asarray(stored)
        if values.dtype.kind in "fc" and not np.isfinite(values).all():
            bad = int(values.size - np.count_nonzero(np.isfinite(values)))
            raise ModelFormatError(
                f"model array {name!r} holds {bad} non-finite value(s) (inf or NaN)", "model")
    numbers = {k: meta.get(k) for k in _META_NUMBERS}
    contour_meta = meta.get("contour_meta")
    if isinstance(contour_meta, dict):
        numbers |= {f"contour_meta.{k}": contour_meta.get(k) for k in ("d0_mm", "f_px")}
    for name, value in numbers.items():
        if isinstance(value, float) and not np.isfinite(value):
            raise ModelFormatError(f"model metadata {name!r} is {value} (not finite)", "model")


def model_from_arrays(arrays: dict[str, NDArray[Any]], meta: dict[str, Any]) -> ObjectModel:
    """Rebuild a model from ``model_to_arrays`` output.

    Raises
    ------
    ModelFormatError
        Unknown schema version, missing/inconsistent arrays, or a float
        array or metadata number that is not finite.
    """
    version = meta.get("schema_version")
    if version != SCHEMA_VERSION:
        raise ModelFormatError(f"unsupported model schema version {version!r}", "model")
    _require_finite(arrays, meta)
    try:
        offs = np.asarray(arrays["mv_feat_offsets"], np.int64)
        eoffs = np.asarray(arrays["mv_edge_offsets"], np.int64)
        members = np.asarray(arrays["mv_n_members"], np.int64)
        per_field = {name: _split(arrays[f"mv_{name}"], offs) for name in _VIEW_FIELDS}
        edge_xy = _split(arrays["mv_edge_xy"], eoffs)
        edge_theta = _split(arrays["mv_edge_theta"], eoffs)
        views = [
            ModelView(
                **{name: per_field[name][i] for name in _VIEW_FIELDS},
                n_members=int(members[i]),
                edge_xy=edge_xy[i],
                edge_theta=edge_theta[i],
            )
            for i in range(len(members))
        ]
        toffs = np.asarray(arrays["tv_edge_offsets"], np.int64)
        training = TrainingViews(
            np.asarray(arrays["tv_R_m2c"], np.float64),
            np.asarray(arrays["tv_azimuth_deg"], np.float64),
            np.asarray(arrays["tv_polar_deg"], np.float64),
            np.asarray(arrays["tv_model_view"], np.int64),
            np.asarray(arrays["tv_sim_to_model"], np.float64),
            _split(arrays["tv_edge_xy"], toffs),
            _split(arrays["tv_edge_theta"], toffs),
        )
        contour = None
        if meta.get("has_contour"):
            contour = {k: arrays[f"contour_{k}"] for k in meta["contour_keys"]}
            contour.update(meta.get("contour_meta", {}))
        return ObjectModel(
            source=str(meta["source"]),
            diameter_mm=float(meta["diameter_mm"]),
            d0_mm=float(meta["d0_mm"]),
            f_train_px=float(meta["f_train_px"]),
            train_size_px=int(meta["train_size_px"]),
            origin_offset_mm=np.asarray(arrays["origin_offset_mm"], np.float64),
            model_views=views,
            training=training,
            mesh_vertices_mm=arrays.get("mesh_vertices_mm"),
            mesh_faces=arrays.get("mesh_faces"),
            mesh_vertex_colours=_mesh_vertex_colours(arrays),
            contour=contour,
            symmetries=np.asarray(arrays["symmetries"], np.float64),
            symmetry_axis=(np.asarray(arrays["symmetry_axis"], np.float64).reshape(6)
                           if "symmetry_axis" in arrays else None),
            colour_histogram=_colour_histogram(arrays),
            default_min_score=float(meta["default_min_score"]),
            config=dict(meta.get("config", {})),
        )
    except (KeyError, IndexError, ValueError, TypeError) as exc:
        raise ModelFormatError(
            f"model arrays are incomplete or inconsistent: {exc}", "model"
        ) from exc


def _symmetry_group(model: ObjectModel) -> Symmetries:
    """:meth:`ObjectModel.symmetry_group`, built."""
    if model.symmetry_axis is None:
        return Symmetries(model.symmetries)
    axis = np.asarray(model.symmetry_axis, np.float64)
    return Symmetries(model.symmetries, axis[:3], axis[3:])


_SYMMETRY_GROUPS: weakref.WeakKeyDictionary[ObjectModel, Symmetries] = (
    weakref.WeakKeyDictionary())

_Derived = TypeVar("_Derived")


def cached_per_model(
    cache: weakref.WeakKeyDictionary[ObjectModel, _Derived], model: ObjectModel,
    build: Callable[[ObjectModel], _Derived],
) -> _Derived:
    """``build(model)``, computed once and kept in ``cache`` while the model lives.

    Search structures derived from a model (alignment index, view templates,
    contour model) are built on first use, not stored in the model file.
    """
    value = cache.get(model)
    if value is None:
        value = build(model)
        cache[model] = value
    return value
