"""Small builders shared by the HTTP tests: meshes, images, waiting for jobs."""

from __future__ import annotations

import io
import json
import struct
import time
from pathlib import Path
from typing import Any

import cv2
import httpx
import numpy as np
import trimesh
from PIL import Image

CAMERA = {"fx": 500.0, "fy": 500.0, "cx": 159.5, "cy": 119.5}

#: Learning options for a real learning job in a second or two: twelve
#: training views of a small render.
FAST_LEARNING: dict[str, Any] = {"max_level": 0, "min_level": 0, "contour_level": 1,
                                 "object_px": 64}


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


def jpeg(width: int = 16, height: int = 16, claimed_size: tuple[int, int] | None = None,
         stray: bytes = b"") -> bytes:
    """A JPEG of a colour gradient, as Pillow writes it (SOI, APP0, ..., SOF0, ...).

    Parameters
    ----------
    width, height : int
        Size of the coded image.
    claimed_size : (width, height), optional
        Written into the frame header (SOF0) instead: a decompression bomb
        when large.
    stray : bytes
        Put between the APP0 segment and the next marker: libjpeg skips
        stray bytes with the warning "extraneous bytes before marker".
    """
    yy, xx = np.mgrid[0:height, 0:width]
    rgb = np.stack([xx * 255 // max(width - 1, 1), yy * 255 // max(height - 1, 1),
                    np.full_like(xx, 128)], axis=-1).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="JPEG", quality=95)
    data = bytearray(buf.getvalue())
    if claimed_size is not None:
        sof = data.find(b"\xff\xc0")
        data[sof + 5:sof + 9] = struct.pack(">HH", claimed_size[1], claimed_size[0])
    assert data[2:4] == b"\xff\xe0"  # APP0 right after SOI
    end_of_app0 = 4 + int.from_bytes(data[4:6], "big")
    data[end_of_app0:end_of_app0] = stray
    return bytes(data)


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


def stored_files(root: Path) -> list[Path]:
    """The files of the store at ``root``, its SQLite database left out (jobs write to it)."""
    return sorted(p.relative_to(root) for p in root.rglob("*")
                  if p.is_file() and "sqlite" not in p.name)
