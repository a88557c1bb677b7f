"""The model warmer: ready models are loaded and prepared before any request asks."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from app.model_warmer import ModelWarmer
from model_store import ModelStore
from tests.app.conftest import LiveServer
from tests.app.learned import LearnedStore, another_barbell, learned_barbell
from viewloc_core import localize as localize_module
from viewloc_core import view_search

__all__ = ["learned_barbell"]


def test_each_ready_model_is_prepared_once_in_the_store_cache(
    learned_barbell: LearnedStore, tmp_path: Path
) -> None:
    store = ModelStore(learned_barbell.copy_to(tmp_path / "var"))
    prepared: list[Any] = []
    warmer = ModelWarmer(store, prepared.append, limit=4)

    assert warmer.step() == [learned_barbell.object_id]
    # The model prepared is the one the store hands to requests.
    assert prepared == [store.load_model(learned_barbell.object_id)]
    assert warmer.step() == []
    assert len(prepared) == 1


def test_no_warming_without_room_in_the_cache(
    learned_barbell: LearnedStore, tmp_path: Path
) -> None:
    store = ModelStore(learned_barbell.copy_to(tmp_path / "var"))
    prepared: list[Any] = []
    warmer = ModelWarmer(store, prepared.append, limit=0)
    warmer.start()
    assert warmer.step() == [] and prepared == []
    warmer.stop()


def test_a_corrupt_model_is_reported_by_the_store_and_skipped(
    learned_barbell: LearnedStore, tmp_path: Path
) -> None:
    root = learned_barbell.copy_to(tmp_path / "var")
    npz = root / "objects" / learned_barbell.object_id / "model.npz"
    data = bytearray(npz.read_bytes())
    data[len(data) // 2] ^= 0xFF
    npz.write_bytes(bytes(data))
    store = ModelStore(root)
    prepared: list[Any] = []

    assert ModelWarmer(store, prepared.append, limit=4).step() == []
    assert prepared == []
    failed = store.get_object(learned_barbell.object_id)
    assert failed.state == "failed" and "corrupt" in (failed.error or "")


def test_a_model_holding_inf_is_reported_by_the_store_and_skipped(
    learned_barbell: LearnedStore, tmp_path: Path
) -> None:
    root = learned_barbell.copy_to(tmp_path / "var")
    store = ModelStore(root)
    model = store.load_model(learned_barbell.object_id)
    # As an older version stored an upload far from the origin: a vertex
    # overflowed float32 to inf, yet the checksums are right.
    vertices = np.array(model.mesh_vertices_mm, copy=True)
    vertices[-1, 2] = np.inf
    broken = another_barbell(root, learned_barbell.object_id,
                             lambda m: dataclasses.replace(m, mesh_vertices_mm=vertices))
    prepared: list[Any] = []

    assert ModelWarmer(store, prepared.append, limit=4).step() == [
        learned_barbell.object_id]
    assert prepared == [store.load_model(learned_barbell.object_id)]
    failed = store.get_object(broken)
    assert failed.state == "failed" and "mesh_vertices_mm" in (failed.error or "")


def test_deleted_objects_are_forgotten(learned_barbell: LearnedStore, tmp_path: Path) -> None:
    store = ModelStore(learned_barbell.copy_to(tmp_path / "var"))
    warmer = ModelWarmer(store, lambda model: None, limit=4)
    assert warmer.step() == [learned_barbell.object_id]
    store.delete_object(learned_barbell.object_id)
    assert warmer.step() == []
    assert warmer._seen == set()


def test_prepare_builds_what_localize_derives_from_a_model(
    learned_barbell: LearnedStore, tmp_path: Path
) -> None:
    store = ModelStore(learned_barbell.copy_to(tmp_path / "var"))
    model = store.load_model(learned_barbell.object_id)
    caches = (localize_module._INDEX_CACHE, view_search._TEMPLATES,
              localize_module._CONTOUR_CACHE, localize_module._SURFACE_CACHE)
    assert not any(model in cache for cache in caches)
    localize_module.prepare(model)
    assert all(model in cache for cache in caches)


def test_the_service_prepares_stored_models_at_start_up(
    learned_barbell: LearnedStore, make_server: Callable[..., LiveServer], tmp_path: Path
) -> None:
    learned_barbell.copy_to(tmp_path / "var")
    srv = make_server()
    store = srv.app.state.store
    deadline = time.monotonic() + 30
    # Asked each time: the model a request would get is the one to be prepared.
    while store.load_model(learned_barbell.object_id) not in view_search._TEMPLATES:
        assert time.monotonic() < deadline, "the stored model was never prepared"
        time.sleep(0.05)
    assert httpx.get(f"{srv.url}/healthz").status_code == 200


def test_warm_once_a_whole_pass_has_gone_through_the_stored_models(
    learned_barbell: LearnedStore, tmp_path: Path
) -> None:
    store = ModelStore(learned_barbell.copy_to(tmp_path / "var"))
    calls: list[Any] = []

    def prepare_failing_once(model: Any) -> None:
        calls.append(model)
        if len(calls) == 1:
            raise RuntimeError("a bug in preparing")

    warmer = ModelWarmer(store, prepare_failing_once, limit=4)
    assert not warmer.warm
    # A pass cut short by an error does not count ...
    with pytest.raises(RuntimeError, match="a bug in preparing"):
        warmer.step()
    assert not warmer.warm
    # ... the next one, which skips the model that failed, does.
    assert warmer.step() == [] and warmer.warm
    assert ModelWarmer(store, prepare_failing_once, limit=0).warm


def test_the_service_is_not_ready_until_the_stored_models_are_prepared(
    learned_barbell: LearnedStore, make_server: Callable[..., LiveServer], tmp_path: Path
) -> None:
    learned_barbell.copy_to(tmp_path / "var")
    srv = make_server()
    store = srv.app.state.store
    # The first look is made at start-up, not an interval later.
    assert srv.app.state.warmer.warm
    assert store.load_model(learned_barbell.object_id) in view_search._TEMPLATES
    r = httpx.get(f"{srv.url}/readyz")
    assert r.status_code == 200 and r.json()["checks"]["models_prepared"] is True
    # A warmer that has not been through the store yet (as one still
    # preparing a large store's models) keeps the service unready.
    srv.app.state.warmer = ModelWarmer(store, localize_module.prepare, limit=4)
    r = httpx.get(f"{srv.url}/readyz")
    assert r.status_code == 503
    assert r.json()["detail"] == "not ready: the stored models are still being prepared"
    assert httpx.get(f"{srv.url}/healthz").status_code == 200
