"""Plain-dict forms of store records and core results, in API.md's shapes.

No pydantic here: the command line prints the same JSON without the service.
"""

from __future__ import annotations

import math
from typing import Any

from model_store import JobRecord, ObjectRecord
from viewloc_core.detection import Detection
from viewloc_core.symmetry import Symmetries


def _f(value: float) -> float:
    """A JSON-safe float (non-finite values would make invalid JSON)."""
    v = float(value)
    return v if math.isfinite(v) else 0.0


def symmetries_dict(sym: Symmetries) -> dict[str, Any]:
    """API ``Object.symmetries``: BOP ``models_info`` form, identity left out, mm."""
    cont = []
    if sym.continuous_axis is not None and sym.continuous_offset is not None:
        cont.append({"axis": [_f(v) for v in sym.continuous_axis],
                     "offset": [_f(v) for v in sym.continuous_offset]})
    return {
        "symmetries_discrete": [[_f(v) for v in T.reshape(16)] for T in sym.discrete[1:]],
        "symmetries_continuous": cont,
    }


def object_dict(rec: ObjectRecord, symmetries: dict[str, Any] | None = None) -> dict[str, Any]:
    """API ``Object``; ``symmetries`` (from :func:`symmetries_dict`) once it is ready."""
    return {
        "object_id": rec.object_id,
        "name": rec.name,
        "state": rec.state,
        "source": rec.source,
        "diameter_mm": _f(rec.diameter_mm),
        "training_views": rec.training_views,
        "model_views": rec.model_views,
        "created_at": rec.created_at,
        "job_id": rec.job_id,
        "error": rec.error,
        "symmetries": symmetries,
        "model_sha256": rec.model_sha256 if rec.state == "ready" else None,
    }


def job_dict(rec: JobRecord) -> dict[str, Any]:
    """API ``Job``."""
    return {
        "job_id": rec.job_id,
        "object_id": rec.object_id,
        "state": rec.state,
        "progress": min(1.0, max(0.0, _f(rec.progress))),
        "stage": rec.stage,
        "error": rec.error,
        "created_at": rec.created_at,
        "started_at": rec.started_at,
        "finished_at": rec.finished_at,
    }


def detection_dict(det: Detection) -> dict[str, Any]:
    """API detection (score, log_probability, model_view, view, similarity, pose, refined)."""
    pose = det.pose
    out: dict[str, Any] = {
        "score": min(1.0, max(0.0, _f(det.score))),
        "log_probability": _f(det.log_probability),
        "model_view": int(det.model_view),
        "view": {"azimuth_deg": _f(det.azimuth_deg), "polar_deg": _f(det.polar_deg)},
        "similarity": {
            "x": _f(det.similarity.x),
            "y": _f(det.similarity.y),
            "angle_deg": _f(det.similarity.angle_deg),
            "scale": _f(det.similarity.scale),
        },
        "pose": {
            "R": [[_f(v) for v in row] for row in pose.R_m2c],
            "t_mm": [_f(v) for v in pose.t_m2c],
            "quaternion_wxyz": [_f(v) for v in pose.quaternion_wxyz],
            "euler_xyz_deg": [_f(v) for v in pose.euler_xyz_deg],
        },
        "refined": bool(det.refined),
        "pose_std": None if det.pose_std is None else [_f(v) for v in det.pose_std],
    }
    if det.object_id is not None:
        out["object_id"] = det.object_id
    return out
