"""A localization's time budget (``options.timeout_ms``) through HTTP."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from tests.app.conftest import LiveServer
from tests.app.helpers import assert_problem
from tests.app.learned import LearnedStore, another_barbell, learned_barbell
from viewloc_client import ViewlocClient
from viewloc_client.image_upload import upload_file

__all__ = ["learned_barbell"]

#: 640x480: larger than the search level, so an image where nothing settles
#: is searched again on the finer level unless the budget is spent.
CAMERA = {"fx": 600.0, "fy": 600.0, "cx": 319.5, "cy": 239.5}
#: Part-free noise: nothing settles there.
NOISE = np.random.default_rng(3).integers(0, 255, (480, 640, 3), dtype=np.uint8)


def _post(srv: LiveServer, path: str, options: dict[str, Any]) -> httpx.Response:
    return httpx.post(f"{srv.url}{path}", files={"image": upload_file(NOISE, "scene")},
                      data={"camera": json.dumps(CAMERA), "options": json.dumps(options)},
                      timeout=60)


@pytest.mark.parametrize("bad", [0, -1.5, "soon", 1e12])
def test_a_bad_budget_is_a_422_naming_it(
    learned_barbell: LearnedStore, make_server: Callable[..., LiveServer], tmp_path: Path,
    bad: Any,
) -> None:
    learned_barbell.copy_to(tmp_path / "var")
    srv = make_server()
    for path in (f"/v1/objects/{learned_barbell.object_id}/localize", "/v1/localize"):
        assert_problem(_post(srv, path, {"timeout_ms": bad}), 422, "options.timeout_ms")


def test_a_spent_budget_is_reported_and_leaves_the_later_objects_unsearched(
    learned_barbell: LearnedStore, make_server: Callable[..., LiveServer], tmp_path: Path,
) -> None:
    root = learned_barbell.copy_to(tmp_path / "var")
    first = learned_barbell.object_id
    second = another_barbell(root, first)
    srv = make_server()
    one = f"/v1/objects/{first}/localize"
    # Without a budget nothing is cut short, and the finer level is searched.
    body = _post(srv, one, {"min_score": 0.0}).json()
    assert body["timed_out"] is False and "finer_search" in body["timing_ms"]
    body = _post(srv, one, {"min_score": 0.0, "timeout_ms": 0.001}).json()
    assert body["timed_out"] is True and "finer_search" not in body["timing_ms"]
    # Several objects share one budget: the first is searched, the rest are
    # skipped once it is spent, whether named or not.
    for options in ({}, {"object_ids": [first, second]}):
        body = _post(srv, "/v1/localize", {**options, "timeout_ms": 0.001}).json()
        assert body["timed_out"] is True
        assert len(body["object_ids"]) == 1
        assert body["skipped"] == [
            {"object_id": ({first, second} - set(body["object_ids"])).pop(),
             "reason": "timed-out",
             "detail": "the time budget (options.timeout_ms) was spent before its search began"}]
    body = _post(srv, "/v1/localize", {"timeout_ms": 1e6}).json()
    assert body["timed_out"] is False and body["skipped"] == []
    assert sorted(body["object_ids"]) == sorted([first, second])
    # The client sends the budget and reads the answer.
    with ViewlocClient(srv.url) as client:
        assert client.localize(first, NOISE, CAMERA, timeout_ms=0.001).timed_out
        assert not client.localize(first, NOISE, CAMERA).timed_out
