"""Run a localizer over a set, score every target, summarise, print, save.

Scoring (definitions in :mod:`viewloc_core.metrics`): per target, the top
detection (highest score) is compared with the truth. A target without a
detection is a miss in every rate and recall and has no g. The paper's
recognition rate is the 2D one; mean and median g are over the 2D-recognized
targets, as in the paper's §5.1. Images without the object (negatives) only
count false positives: any returned detection is one.

Images with several instances of the object (the multi set, k > 1 targets)
ask the localizer for k detections and pair them with the targets
(:func:`assign_detections`): best score first, each detection goes to the
nearest target it recognizes in 2D that has none yet; one that recognizes
only targets already taken is a duplicate, one that recognizes none lies
elsewhere. Each target is then scored with its own detection, or is a miss.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image

from viewloc_bench.localizers import Backend, LearnedObject
from viewloc_bench.sets import BenchImage, BenchObject, BenchSet, Target
from viewloc_core import metrics as vm
from viewloc_core.camera import Camera
from viewloc_core.detection import Detection

Record = dict[str, Any]

#: A detection at the right place (``recognized_2d``) whose rotation is
#: further than this from the truth (symmetries allowed for) is counted as
#: turned: a part seen from its other side, not a pose a degree or two off.
TURNED_DEG = 30.0


def score_target(
    target: Target, obj: BenchObject, image: BenchImage, dets: list[Detection], latency_ms: float
) -> Record:
    """Metrics of the top detection against one target with a pose."""
    assert target.pose is not None
    cam = image.camera
    rec: Record = {
        "image": image.path.name,
        "object": target.object_name,
        "group": target.group,
        "n_clutter": target.n_clutter,
        "visible_fraction": target.visible_fraction,
        "latency_ms": round(latency_ms, 3),
        "detected": bool(dets),
        "image_diameter_px": vm.image_diameter_px(cam, target.pose, obj.diameter_mm),
        "conditions": dict(target.conditions),
    }
    if not dets:
        rec.update(recognized_2d=False, recognized_6d=False)
        return rec
    det = max(dets, key=lambda d: d.score)
    xy = np.array([det.similarity.x, det.similarity.y])
    dz, dxy, da = vm.paper_deltas(det.pose, target.pose, obj.symmetries)
    e_mssd = vm.mssd(det.pose, target.pose, obj.pts_obj, obj.symmetries)
    rec.update(
        score=det.score,
        refined=det.refined,
        ref_err_px=vm.reference_point_error_px(xy, cam, target.pose),
        recognized_2d=vm.recognized_2d(xy, cam, target.pose, obj.diameter_mm),
        dz_mm=dz,
        depth_mm=float(target.pose.t_m2c[2]),
        dxy_mm=dxy,
        dalpha_deg=da,
        g=vm.g_from_deltas(dz, dxy, da),
        mssd_mm=e_mssd,
        mspd_px=vm.mspd(det.pose, target.pose, obj.pts_obj, cam, obj.symmetries),
        adds_mm=vm.add_s(det.pose, target.pose, obj.pts_obj),
        recognized_6d=vm.recognized_6d(e_mssd, obj.diameter_mm),
    )
    return rec


def assign_detections(
    dets: list[Detection], targets: list[Target], obj: BenchObject, camera: Camera
) -> tuple[list[Detection | None], int, int]:
    """Pair the detections of one image with its instances of the object (module doc).

    Parameters
    ----------
    dets : list of Detection
        In any order; taken best score first.
    targets : list of Target
        The instances, each with a pose.

    Returns
    -------
    assigned : list of Detection or None
        Per target, its detection (None: a miss).
    duplicates : int
        Detections that recognize only targets taken by better ones.
    elsewhere : int
        Detections that recognize no target in 2D.
    """
    assigned: list[Detection | None] = [None] * len(targets)
    duplicates = elsewhere = 0
    for det in sorted(dets, key=lambda d: d.score, reverse=True):
        xy = np.array([det.similarity.x, det.similarity.y])
        hits = []
        for i, t in enumerate(targets):
            assert t.pose is not None
            if vm.recognized_2d(xy, camera, t.pose, obj.diameter_mm):
                hits.append((vm.reference_point_error_px(xy, camera, t.pose), i))
        free = [(err, i) for err, i in hits if assigned[i] is None]
        if free:
            assigned[min(free)[1]] = det
        elif hits:
            duplicates += 1
        else:
            elsewhere += 1
    return assigned, duplicates, elsewhere


def _score_instances(
    targets: list[Target],
    obj: BenchObject,
    image: BenchImage,
    dets: list[Detection],
    latency_ms: float,
    tally: Record,
) -> list[Record]:
    """Records of an image's instances of one object, each scored with its own detection.

    ``tally`` (the set's ``copies`` summary, see :func:`evaluate_set`) gains
    the image's counts.
    """
    assigned, duplicates, elsewhere = assign_detections(dets, targets, obj, image.camera)
    k = len(targets)
    tally["images"] += 1
    tally["per_image"] = sorted({*tally["per_image"], k})
    tally["targets"] += k
    tally["found_2d"] += sum(d is not None for d in assigned)
    tally["detections"] += len(dets)
    tally["duplicates"] += duplicates
    tally["elsewhere"] += elsewhere
    records = []
    for t, det in zip(targets, assigned, strict=True):
        records.append(score_target(t, obj, image, [det] if det else [], latency_ms))
        records[-1]["copies"] = k
    return records


def _nan_to_none(x: float) -> float | None:
    return None if (x is None or not math.isfinite(x)) else round(float(x), 4)


def summarise(records: list[Record], objects: dict[str, BenchObject], width: int) -> Record:
    """Rates, g statistics, BOP average recalls, ADD-S recall and latency of some
    targets; ``timed_out``: how many had a search left out for the time budget
    (only when any had)."""
    n = len(records)
    out: Record = {"targets": n}
    if n == 0:
        return out
    rec2d = np.array([r["recognized_2d"] for r in records], dtype=bool)
    rec6d = np.array([r["recognized_6d"] for r in records], dtype=bool)
    g = np.array([r["g"] for r, ok in zip(records, rec2d, strict=True) if ok], dtype=np.float64)
    inf = float("inf")
    mssd = np.array([r.get("mssd_mm", inf) for r in records], dtype=np.float64)
    mspd = np.array([r.get("mspd_px", inf) for r in records], dtype=np.float64)
    adds = np.array([r.get("adds_mm", inf) for r in records], dtype=np.float64)
    diam = np.array([objects[r["object"]].diameter_mm for r in records], dtype=np.float64)
    lat = np.array([r["latency_ms"] for r in records], dtype=np.float64)
    out.update(
        detected=round(float(np.mean([r["detected"] for r in records])), 4),
        recognition_2d=round(float(rec2d.mean()), 4),
        recognition_6d=round(float(rec6d.mean()), 4),
        mean_g=_nan_to_none(float(g.mean())) if len(g) else None,
        median_g=_nan_to_none(float(np.median(g))) if len(g) else None,
        ar_mssd=round(vm.average_recall(mssd, diam[:, None] * vm.MSSD_THRESHOLDS_REL[None]), 4),
        ar_mspd=round(vm.average_recall(mspd, vm.mspd_thresholds_px(width)), 4),
        adds_recall=round(float(vm.recall_at(adds, (diam * vm.ADDS_THRESHOLD_REL)[:, None])[0]), 4),
        latency_median_ms=round(float(np.median(lat)), 2),
        latency_p95_ms=round(float(np.percentile(lat, 95)), 2),
    )
    server = [r["timing_ms"]["server_total"] for r in records
              if "server_total" in r.get("timing_ms", {})]
    if server:
        out.update(
            server_total_median_ms=round(float(np.median(server)), 2),
            server_total_p95_ms=round(float(np.percentile(server, 95)), 2),
        )
    stages = stage_medians_ms(records)
    if stages:
        out["stage_median_ms"] = stages
    timed_out = sum(1 for r in records if r.get("timed_out"))
    if timed_out:
        out["timed_out"] = timed_out
    out.update(right_place_errors(records))
    return out


def right_place_errors(records: list[Record]) -> Record:
    """What keeps the detections at the right place from being right in 6D:
    the share of them turned more than :data:`TURNED_DEG`
    (``turned_share``) and their median depth error as a share of the
    part's true depth (``median_depth_error_rel``, the pose's error along the
    line of sight, which an outline pins least). Empty without any such
    detection; ``median_depth_error_rel`` only for records with ``depth_mm``."""
    right = [r for r in records if r.get("recognized_2d") and "dalpha_deg" in r]
    if not right:
        return {}
    out: Record = {"turned_share": round(
        float(np.mean([r["dalpha_deg"] > TURNED_DEG for r in right])), 4)}
    depth = [r["dz_mm"] / r["depth_mm"] for r in right if r.get("depth_mm")]
    if depth:
        out["median_depth_error_rel"] = round(float(np.median(depth)), 5)
    return out


def stage_medians_ms(records: list[Record]) -> dict[str, float]:
    """Median of each stage time the backend reported (a record's
    ``timing_ms``: the core's ``features``, ``align``, ``views``, ``pose``,
    ``total``; the HTTP client's and server's), over the records that have
    it, ms; stages in the order they were first reported, empty without any."""
    times: dict[str, list[float]] = {}
    for r in records:
        for stage, ms in r.get("timing_ms", {}).items():
            times.setdefault(stage, []).append(float(ms))
    return {stage: round(float(np.median(v)), 2) for stage, v in times.items()}


def summarise_conditions(records: list[Record], objects: dict[str, BenchObject],
                         width: int) -> dict[str, list[Record]]:
    """The summary of the targets under each value of each scene condition.

    Returns
    -------
    dict
        Condition name (``background``, ``material``, ...) -> one summary per
        value, with a ``value`` field, in the order of the values' names.
        Where a set fails (chequered floors, metal, fog) is the first thing
        to know when improving the method.
    """
    values: dict[str, set[str]] = {}
    for r in records:
        for key, value in r.get("conditions", {}).items():
            values.setdefault(key, set()).add(value)
    return {
        key: [
            {"value": v, **summarise([r for r in records if r.get("conditions", {}).get(key) == v],
                                     objects, width)}
            for v in sorted(vs)
        ]
        for key, vs in values.items()
    }


#: Lower bounds of the visible-fraction bands of :func:`summarise_visibility`;
#: each band runs to the next bound, the last to 1 inclusive. A part more
#: than 60 % hidden has lost most of its outline, one at least 90 % visible
#: is practically whole; BOP scores targets from 10 % visible.
VISIBILITY_BANDS = (0.0, 0.4, 0.7, 0.9)


def summarise_visibility(records: list[Record], objects: dict[str, BenchObject],
                         width: int) -> list[Record]:
    """The summary of the targets in each band of visible fraction
    (:data:`VISIBILITY_BANDS`), overall and per object.

    Where a set's misses lie by occlusion tells a part that is lost only
    where it is hidden from one that is lost in full view too (LM-O
    objects 1, 5, 6, 8, learning seed 0: the cat right in 2D in all 69
    photos showing at least 90 % of it, the driller in 7 of 49), the first
    thing to know before improving the method on it.

    Returns
    -------
    list of dict
        One per band that holds a target, in order: ``from`` and ``to``
        (the band's bounds, visible fraction), the :func:`summarise` fields
        and ``per_object`` (object name -> :func:`summarise` of its targets
        in the band). Targets with no visible fraction are left out.
    """
    bounds = [*VISIBILITY_BANDS, math.inf]
    out: list[Record] = []
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        band = [r for r in records if r.get("visible_fraction") is not None
                and lo <= r["visible_fraction"] < hi]
        if not band:
            continue
        names = sorted({r["object"] for r in band})
        out.append({
            "from": lo, "to": min(hi, 1.0), **summarise(band, objects, width),
            "per_object": {name: summarise([r for r in band if r["object"] == name],
                                           objects, width) for name in names},
        })
    return out


def _false_positives_by(negatives: list[Record], key: str) -> dict[str, list[int]]:
    """Condition value -> [images with a false positive, images] among the negatives."""
    out: dict[str, list[int]] = {}
    for r in negatives:
        value = r.get("conditions", {}).get(key)
        if value is not None:
            counts = out.setdefault(value, [0, 0])
            counts[0] += int(r["detections"] > 0)
            counts[1] += 1
    return dict(sorted(out.items()))


def _group_key(group: str) -> tuple[int, str]:
    if group.startswith("N="):
        return (int(group[2:]), group)
    return (10**6, group)


def evaluate_set(
    bench: BenchSet,
    backend: Backend,
    log: Callable[[str], None] = print,
    learned_cache: dict[str, LearnedObject] | None = None,
) -> Record:
    """Learn each object of a set, localize it in every image it belongs to, score.

    Returns
    -------
    dict
        ``objects`` (learning figures), ``groups`` (per object and group),
        ``overall``, ``per_object``, ``by_condition`` (see
        :func:`summarise_conditions`), ``by_visibility`` (see
        :func:`summarise_visibility`), ``negatives`` and ``records``; with
        ``copies`` when some image holds several instances of its object:
        ``images`` such images, ``per_image`` (the instance counts seen),
        ``targets``, ``found_2d`` (targets that got a detection),
        ``detections``, ``duplicates`` and ``elsewhere`` (see
        :func:`assign_detections`).
    """
    width = bench.images[0].camera.width if bench.images else 640
    records: list[Record] = []
    negatives: list[Record] = []
    learned_info: dict[str, Record] = {}
    copies: Record = {"images": 0, "per_image": [], "targets": 0, "found_2d": 0,
                      "detections": 0, "duplicates": 0, "elsewhere": 0}
    for name, obj in bench.objects.items():
        imgs = [im for im in bench.images if any(t.object_name == name for t in im.targets)]
        if not imgs:
            continue
        if learned_cache is not None and name in learned_cache:
            learned = learned_cache[name]
        else:
            log(f"  learning {name} ...")
            learned = backend.learn(obj)
            if learned_cache is not None:
                learned_cache[name] = learned
        learned_info[name] = {
            "learn_s": round(learned.learn_s, 2),
            "training_views": learned.training_views,
            "model_views": learned.model_views,
            **learned.info,
        }
        log(
            f"  {name}: learned in {learned.learn_s:.1f} s, training views "
            f"{learned.training_views}, model views {learned.model_views}"
            + _model_checksum_note(learned.info)
        )
        for im in imgs:
            with Image.open(im.path) as pil:
                image = np.asarray(pil.convert("RGB"), dtype=np.uint8)
            posed = [t for t in im.targets if t.object_name == name and t.pose is not None]
            k = len(posed)
            t0 = time.perf_counter()
            # One instance: called as always (localizers without max_detections keep working).
            dets = (learned.localize(image, im.camera) if k <= 1
                    else learned.localize(image, im.camera, max_detections=k))
            latency_ms = (time.perf_counter() - t0) * 1000.0
            # Backends that can tell where the time went (HTTP: server timing_ms).
            breakdown = dict(getattr(learned.localize, "last_timing_ms", None) or {})
            # Only with a time budget: the search left something out for it.
            cut = {"timed_out": True} if getattr(learned.localize, "last_timed_out",
                                                 False) else {}
            if k > 1:
                records += _score_instances(posed, obj, im, dets, latency_ms, copies)
                for r in records[-k:]:
                    r.update(cut)
                    if breakdown:
                        r["timing_ms"] = breakdown
                continue
            for t in im.targets:
                if t.object_name != name:
                    continue
                if t.pose is None:
                    negatives.append(
                        {
                            "image": im.path.name,
                            "object": name,
                            "detections": len(dets),
                            "top_score": max((d.score for d in dets), default=None),
                            "latency_ms": round(latency_ms, 3),
                            "conditions": dict(t.conditions),
                            **cut,
                        }
                    )
                else:
                    records.append({**score_target(t, obj, im, dets, latency_ms), **cut})
                    if breakdown:
                        records[-1]["timing_ms"] = breakdown
    groups = []
    keys = sorted(
        {(r["object"], r["group"]) for r in records}, key=lambda k: (k[0], _group_key(k[1]))
    )
    for obj_name, group in keys:
        sub = [r for r in records if r["object"] == obj_name and r["group"] == group]
        groups.append({"object": obj_name, "group": group, **summarise(sub, bench.objects, width)})
    per_object = {
        o: summarise([r for r in records if r["object"] == o], bench.objects, width)
        for o in bench.objects
    }
    overall = summarise(records, bench.objects, width)
    rec_by_n: dict[str, list[float]] = {}
    for g in groups:
        rec_by_n.setdefault(g["group"], []).append(g["recognition_2d"])
    if rec_by_n:
        overall["worst_group_recognition_2d"] = round(min(min(v) for v in rec_by_n.values()), 4)
    neg = {
        "images": len(negatives),
        "images_with_false_positive": sum(1 for r in negatives if r["detections"] > 0),
        "false_positives": sum(r["detections"] for r in negatives),
        "by_background": _false_positives_by(negatives, "background"),
    }
    result = {
        "objects": learned_info,
        "groups": groups,
        "per_object": per_object,
        "by_condition": summarise_conditions(records, bench.objects, width),
        "by_visibility": summarise_visibility(records, bench.objects, width),
        "overall": overall,
        "negatives": neg,
        "records": records,
        "negative_records": negatives,
    }
    if copies["images"]:
        result["copies"] = copies
    return result


def _fmt(x: Any, spec: str = ".3f") -> str:
    if x is None:
        return "-"
    if isinstance(x, float):
        return format(x, spec)
    return str(x)


def _model_checksum_note(info: Record) -> str:
    """``, model sha256 <first 16 hex digits>`` when the backend knows the
    learned model's checksum (:func:`model_store.files.model_sha256`, the
    API's ``Object.model_sha256``), else nothing."""
    digest = info.get("model_sha256")
    return f", model sha256 {digest[:16]}" if digest else ""


def _rate_of(summary: Record) -> str:
    """A breakdown's entry: its 2D recognition rate and (in brackets) its targets."""
    return f"{_fmt(summary.get('recognition_2d'), '.2f')} ({summary['targets']})"


def format_table(name: str, bench: BenchSet, result: Record | None, header: str) -> str:
    """The printed table of one set (``result`` None: only the set's composition)."""
    lines = [f"== {name} set: {header} =="]
    lines.append(
        f"{'object':<12} {'group':<9} {'images':>6} {'rec2D':>6} {'rec6D':>6} "
        f"{'mean g':>7} {'med g':>7} {'AR_MSSD':>8} {'AR_MSPD':>8} {'ADD-S':>6}"
    )
    if result is None:
        counts: dict[tuple[str, str], int] = {}
        for im in bench.images:
            for t in im.targets:
                if t.pose is not None:
                    counts[(t.object_name, t.group)] = counts.get((t.object_name, t.group), 0) + 1
        for (obj, group), c in sorted(
            counts.items(), key=lambda kv: (kv[0][0], _group_key(kv[0][1]))
        ):
            lines.append(
                f"{obj:<12} {group:<9} {c:>6} {'-':>6} {'-':>6} {'-':>7} {'-':>7} "
                f"{'-':>8} {'-':>8} {'-':>6}"
            )
        lines.append("engine not available: sets generated, nothing measured")
        return "\n".join(lines)
    for g in result["groups"]:
        lines.append(
            f"{g['object']:<12} {g['group']:<9} {g['targets']:>6} "
            f"{_fmt(g.get('recognition_2d'), '.2f'):>6} {_fmt(g.get('recognition_6d'), '.2f'):>6} "
            f"{_fmt(g.get('mean_g')):>7} {_fmt(g.get('median_g')):>7} "
            f"{_fmt(g.get('ar_mssd')):>8} {_fmt(g.get('ar_mspd')):>8} "
            f"{_fmt(g.get('adds_recall'), '.2f'):>6}"
        )
    o = result["overall"]
    lines.append(
        f"{'overall':<12} {'all':<9} {o['targets']:>6} {_fmt(o.get('recognition_2d'), '.2f'):>6} "
        f"{_fmt(o.get('recognition_6d'), '.2f'):>6} {_fmt(o.get('mean_g')):>7} "
        f"{_fmt(o.get('median_g')):>7} {_fmt(o.get('ar_mssd')):>8} {_fmt(o.get('ar_mspd')):>8} "
        f"{_fmt(o.get('adds_recall'), '.2f'):>6}"
    )
    neg = result["negatives"]
    lines.append(
        f"worst-group rec2D {_fmt(o.get('worst_group_recognition_2d'), '.2f')}; latency median "
        f"{_fmt(o.get('latency_median_ms'), '.1f')} ms, "
        f"p95 {_fmt(o.get('latency_p95_ms'), '.1f')} ms"
        + (f" (server total median {_fmt(o.get('server_total_median_ms'), '.1f')} ms, "
           f"p95 {_fmt(o.get('server_total_p95_ms'), '.1f')} ms)"
           if "server_total_median_ms" in o else "")
        + "; "
        f"false positives: {neg['false_positives']} in {neg['images_with_false_positive']}"
        f"/{neg['images']} images without the object"
    )
    if o.get("stage_median_ms"):
        lines.append("stage medians: " + ", ".join(
            f"{stage} {ms:.1f}" for stage, ms in o["stage_median_ms"].items()) + " ms")
    if o.get("timed_out"):
        lines.append(f"time budget: a search left out for {o['timed_out']} of "
                     f"{o['targets']} targets")
    if "turned_share" in o:
        lines.append(
            f"right place: {100 * o['turned_share']:.0f}% turned over {TURNED_DEG:.0f} deg"
            + (f", median depth error {100 * o['median_depth_error_rel']:.2f}%"
               if "median_depth_error_rel" in o else ""))
    if "copies" in result:
        c = result["copies"]
        lines.append(
            f"copies: {'/'.join(str(k) for k in c['per_image'])} per image, {c['images']} images: "
            f"{c['found_2d']}/{c['targets']} found in 2D, {c['duplicates']} duplicates, "
            f"{c['elsewhere']} elsewhere"
        )
    for key, rows in result.get("by_condition", {}).items():
        lines.append(f"rec2D by {key}: "
                     + ", ".join(f"{r['value']} {_rate_of(r)}" for r in rows))
    bands = result.get("by_visibility", [])
    if len(bands) > 1:
        # One band says nothing more than the overall line.
        lines.append("rec2D by visible fraction: " + ", ".join(
            f"{b['from']:g}-{b['to']:g} {_rate_of(b)}" for b in bands))
        for name in sorted({n for b in bands for n in b["per_object"]}):
            lines.append(f"  {name}: " + ", ".join(
                f"{b['from']:g}-{b['to']:g} {_rate_of(b['per_object'][name])}"
                for b in bands if name in b["per_object"]))
    if neg.get("by_background"):
        lines.append(
            "images with a false positive by background: "
            + ", ".join(f"{v} {k}/{n}" for v, (k, n) in neg["by_background"].items())
        )
    for obj_name, info in result["objects"].items():
        lines.append(
            f"learned {obj_name}: {info['learn_s']:.1f} s, training views {info['training_views']},"
            f" model views {info['model_views']}" + _model_checksum_note(info)
        )
    return "\n".join(lines)


def plot_fig2(result: Record, path: Path) -> None:
    """Recognition rate and mean g against the number of clutter objects (paper Fig. 2)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [g for g in result["groups"] if g["group"].startswith("N=")]
    n = [int(g["group"][2:]) for g in rows]
    fig, ax = plt.subplots(figsize=(6, 4), dpi=110)
    ax.plot(n, [g["recognition_2d"] for g in rows], "o-", label="recognition rate (2D)")
    ax.plot(n, [g["recognition_6d"] for g in rows], "s--", label="recognition rate (6D, MSSD<0.1d)")
    ax.plot(
        n,
        [g["mean_g"] if g["mean_g"] is not None else np.nan for g in rows],
        "^-",
        label="mean g(L,T) if recognized",
    )
    ax.set_xlabel("Number of random clutter objects")
    ax.set_ylim(0.0, 1.05)
    ax.set_xticks(n)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="lower left", fontsize=8)
    ax.set_title("Barbell among clutter (cf. paper Fig. 2)")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def write_json(results: Record, path: Path) -> None:
    """Write results, turning numpy scalars and non-finite floats into JSON values."""

    def clean(x: Any) -> Any:
        if isinstance(x, dict):
            return {str(k): clean(v) for k, v in x.items()}
        if isinstance(x, list | tuple):
            return [clean(v) for v in x]
        if isinstance(x, np.generic):
            x = x.item()
        if isinstance(x, float):
            return x if math.isfinite(x) else None
        if isinstance(x, Path):
            return str(x)
        return x

    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(clean(results), indent=1))
