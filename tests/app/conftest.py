"""A real uvicorn server on a free loopback port, per test, with its own store."""

from __future__ import annotations

import shutil
import socket
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import uvicorn

from app.main import create_app
from app.settings import Settings

TEST_TASKS = {
    "sleepy": "tests.app.job_funcs:sleepy",
    "crash": "tests.app.job_funcs:crash",
    "bad_input": "tests.app.job_funcs:bad_input",
    "ignores_cancel": "tests.app.job_funcs:ignores_cancel",
}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class LiveServer:
    url: str
    app: Any
    server: uvicorn.Server
    thread: threading.Thread

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(20)


def start_server(settings: Settings, tasks: dict[str, str] | None = None) -> LiveServer:
    app = create_app(settings, tasks=tasks)
    port = free_port()
    config = uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning",
                            lifespan="on")
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    # Start-up compiles the numba kernels when their cache is stale (after
    # an edit of a kernel module: about 35 s on 2 cores).
    deadline = time.monotonic() + 120
    while not server.started:
        if time.monotonic() > deadline or not thread.is_alive():
            raise RuntimeError("uvicorn did not start")
        time.sleep(0.02)
    # Ready as a client would wait for it: the stored models prepared (an
    # empty store's first look takes milliseconds), so /readyz answers 200.
    while not app.state.warmer.warm:
        if time.monotonic() > deadline or not thread.is_alive():
            raise RuntimeError("the stored models were not prepared")
        time.sleep(0.02)
    return LiveServer(f"http://127.0.0.1:{port}", app, server, thread)


@pytest.fixture(scope="session")
def redis_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A real redis-server on a free loopback port, without persistence, for the
    whole session; yields ``redis://127.0.0.1:<port>`` (tests pick a db number)."""
    binary = shutil.which("redis-server")
    if binary is None:
        pytest.skip("redis-server is not installed (scripts/setup.sh installs it)")
    port = free_port()
    workdir = tmp_path_factory.mktemp("redis")
    proc = subprocess.Popen(
        [binary, "--port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
         "--dir", str(workdir), "--databases", "64", "--protected-mode", "yes"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + 10
    while True:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=1) as s:
                s.sendall(b"PING\r\n")
                if s.recv(16).startswith(b"+PONG"):
                    break
        except OSError:
            pass
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            raise RuntimeError("redis-server did not start")
        time.sleep(0.05)
    yield f"redis://127.0.0.1:{port}"
    proc.terminate()
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()


@pytest.fixture
def make_server(tmp_path: Path) -> Iterator[Callable[..., LiveServer]]:
    """Start servers on tmp_path/var (same root for every call: restarts share it)."""
    started: list[LiveServer] = []

    def make(tasks: dict[str, str] | None = None, **overrides: Any) -> LiveServer:
        values: dict[str, Any] = {"data_dir": tmp_path / "var", "log_json": True,
                                  "job_stale_after_s": 5.0, "job_cancel_grace_s": 1.0}
        values.update(overrides)
        srv = start_server(Settings(**values), tasks)
        started.append(srv)
        return srv

    yield make
    for srv in started:
        srv.stop()
