"""Small builders shared by the HTTP tests: meshes, images, waiting for jobs."""

from __future__ import annotations

import json
import time
from typing import Any

import cv2
import httpx
import numpy as np
import trimesh

CAMERA = {"fx": 500.0, "fy": 500.0, "cx": 159.5, "cy": 119.5}


def box_stl() -> bytes:
    data = trimesh.creation.box((40.0, 20.0, 10.0)).export(file_type="stl")
    return bytes(data)


def png(width: int = 320, height: int = 240, channels: int = 3, dtype: Any = np.uint8,
        noise: bool = True) -> bytes:
    rng = np.random.default_rng(0)
    shape = (height, width) if channels == 1 else (height, width, channels)
    top = 255 if dtype == np.uint8 else 65535
    img = (rng.integers(0, top, size=shape, endpoint=True) if noise
           else np.zeros(shape)).astype(dtype)
    ok, buf = cv2.imencode(".png", img)
    assert ok
    return bytes(buf.tobytes())


def upload_mesh(client: httpx.Client, data: bytes | None = None, name: str = "box",
                filename: str = "box.stl") -> httpx.Response:
    return client.post(
        "/v1/objects",
        files={"mesh": (filename, data if data is not None else box_stl(),
                        "application/octet-stream")},
        data={"spec": json.dumps({"name": name, "units": "mm"})},
    )


def wait_job(client: httpx.Client, job_id: str, states: tuple[str, ...] = (
        "succeeded", "failed", "cancelled"), timeout: float = 60.0) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while True:
        job: dict[str, Any] = client.get(f"/v1/jobs/{job_id}").json()
        if job["state"] in states:
            return job
        assert time.monotonic() < deadline, f"job stuck: {job}"
        time.sleep(0.1)


def assert_problem(r: httpx.Response, status: int, field: str | None = None) -> dict[str, Any]:
    assert r.status_code == status, (r.status_code, r.text)
    assert r.headers["content-type"].startswith("application/problem+json"), r.headers
    body: dict[str, Any] = r.json()
    assert body["status"] == status
    assert {"type", "title", "detail"} <= set(body)
    if field is not None:
        assert any(e["field"] == field for e in body.get("errors", [])), body
    return body
