"""Run the service in its own process, with the test job kinds (for kill -9 tests)."""

from __future__ import annotations

import argparse

import uvicorn

from app.main import create_app
from app.settings import Settings
from tests.app.conftest import TEST_TASKS


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--data-dir", required=True)
    parser.add_argument("--learn-mesh-task", default="sleepy")
    args = parser.parse_args()
    tasks = {**TEST_TASKS, "learn_mesh": TEST_TASKS[args.learn_mesh_task]}
    settings = Settings(data_dir=args.data_dir, job_stale_after_s=5.0)
    uvicorn.run(create_app(settings, tasks=tasks), host="127.0.0.1", port=args.port,
                log_level="warning")


if __name__ == "__main__":
    main()
