"""Property-based run of schemathesis against the served /openapi.json (loopback only)."""

from __future__ import annotations

from collections.abc import Callable

import pytest
import schemathesis
from hypothesis import HealthCheck, Phase, given, settings
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    response_schema_conformance,
    status_code_conformance,
)

from tests.app.conftest import TEST_TASKS, LiveServer

CHECKS = (not_a_server_error, status_code_conformance, content_type_conformance,
          response_schema_conformance)


def test_no_5xx_and_no_schema_violations(make_server: Callable[..., LiveServer]) -> None:
    srv = make_server(tasks={**TEST_TASKS, "learn_mesh": TEST_TASKS["sleepy"]},
                      max_images=4, max_image_pixels=1_000_000)
    schema = schemathesis.openapi.from_url(f"{srv.url}/openapi.json")
    failures: list[str] = []
    ran = 0
    statuses: list[int] = []
    for op in schema.get_all_operations():
        operation = op.ok()

        @settings(max_examples=15, deadline=None, database=None, derandomize=True,
                  phases=[Phase.explicit, Phase.generate],
                  suppress_health_check=list(HealthCheck))
        @given(case=operation.as_strategy())
        def check(case: schemathesis.Case) -> None:
            response = case.call(base_url=srv.url, timeout=30)
            statuses.append(response.status_code)
            case.validate_response(response, checks=CHECKS)

        try:
            check()
            ran += 1
        except Exception as exc:  # collect every operation's failure, not just the first
            failures.append(f"{operation.label}: {exc}")
    assert ran >= 9 and len(statuses) > 60
    assert any(200 <= s < 300 for s in statuses) and any(400 <= s < 500 for s in statuses)
    if failures:
        pytest.fail("\n\n".join(failures))
