"""Deployment files: compose structure, settings documented, image build steps shared with CI.

Docker is not available where the tests run, so the compose file is checked
structurally here (services, shared store volume, backend wiring, health
checks, interpolated settings) instead of with ``docker compose config``.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path
from typing import Any

import yaml

from app.settings import Settings

REPO = Path(__file__).resolve().parents[1]


def _compose() -> dict[str, Any]:
    data: dict[str, Any] = yaml.safe_load((REPO / "docker-compose.yml").read_text())
    return data


def _env(service: dict[str, Any]) -> dict[str, str]:
    env = service.get("environment", {})
    assert isinstance(env, dict), "environment as a mapping"
    return {str(k): str(v) for k, v in env.items()}


def _setting_vars() -> set[str]:
    return {f"VIEWLOC_{name.upper()}" for name in Settings.model_fields}


def test_compose_services_volume_backend_and_healthchecks() -> None:
    compose = _compose()
    services = compose["services"]
    assert {"api", "worker", "redis", "proxy"} <= set(services)
    assert "viewloc-data" in compose["volumes"]
    for name in ("api", "worker"):
        svc = services[name]
        assert "viewloc-data:/data" in svc["volumes"], name
        env = _env(svc)
        assert env["VIEWLOC_DATA_DIR"] == "/data"
        assert env["VIEWLOC_JOB_BACKEND"] == "redis"
        assert "redis://redis:6379" in env["VIEWLOC_REDIS_URL"]
        # Every service setting reaches the containers (interpolated from .env).
        assert _setting_vars() <= set(env), _setting_vars() - set(env)
        assert svc["depends_on"]["redis"]["condition"] == "service_healthy"
        assert str(svc["deploy"]["replicas"]).startswith("${"), "replicas from .env"
    assert services["api"]["image"] == services["worker"]["image"]
    assert services["api"]["build"] == "."
    assert services["worker"]["command"][-3:] == ["-m", "viewloc_cli", "worker"]
    # Only the proxy publishes a port; the API replicas sit behind it.
    assert "ports" not in services["api"]
    assert services["proxy"]["ports"] == ["${PORT:-8000}:8080"]
    assert services["proxy"]["depends_on"]["api"]["condition"] == "service_healthy"
    for name, svc in services.items():
        test = svc["healthcheck"]["test"]
        assert test[0] == "CMD" and len(test) > 1, name
    assert "/healthz" in " ".join(services["api"]["healthcheck"]["test"])
    assert services["redis"]["healthcheck"]["test"][1:] == ["redis-cli", "ping"]
    mounted = [v.split(":")[0] for v in services["proxy"]["volumes"]]
    for path in mounted:
        assert (REPO / path).is_file(), path


def test_proxy_balances_over_the_api_service() -> None:
    conf = (REPO / "deploy" / "nginx.conf").read_text()
    assert re.search(r"listen 8080;", conf)
    assert "resolver 127.0.0.11" in conf  # re-resolves replicas through Docker's DNS
    assert re.search(r"set \$viewloc_api http://api:8000;", conf)
    assert "proxy_pass $viewloc_api;" in conf
    assert conf.count("{") == conf.count("}")


def test_env_example_documents_every_setting() -> None:
    text = (REPO / ".env.example").read_text()
    documented = dict(re.findall(r"^([A-Z_]+)=(.*)$", text, flags=re.MULTILINE))
    missing = (_setting_vars() | {"PORT", "API_REPLICAS", "WORKER_REPLICAS",
                                  "VIEWLOC_HTTP_WORKERS"}) - set(documented)
    assert not missing, missing
    # The example values are the defaults and parse as settings.
    values = {k[len("VIEWLOC_"):].lower(): v for k, v in documented.items()
              if k.startswith("VIEWLOC_") and k[len("VIEWLOC_"):].lower() in Settings.model_fields}
    parsed = Settings(**values)  # type: ignore[arg-type]
    defaults = Settings()
    for name in Settings.model_fields:
        if name not in ("redis_url",):  # the example names the compose service
            assert getattr(parsed, name) == getattr(defaults, name), name


def test_dockerfile_is_multi_stage_nonroot_and_installs_through_setup_sh() -> None:
    text = (REPO / "Dockerfile").read_text()
    assert len(re.findall(r"^FROM ", text, flags=re.MULTILINE)) == 2
    assert "AS builder" in text
    assert "scripts/setup.sh --python-only" in text
    assert "scripts/setup.sh --system-only" in text
    assert "COPY --from=builder /app /app" in text
    assert re.search(r"^USER viewloc$", text, flags=re.MULTILINE)
    assert 'VOLUME ["/data"]' in text
    assert re.search(r"^HEALTHCHECK .*", text, flags=re.MULTILINE)
    assert "/healthz" in text
    ignore = (REPO / ".dockerignore").read_text().split()
    assert {".git", ".venv", "var", "bench_out", "tests"} <= set(ignore)


def test_setup_sh_modes() -> None:
    script = REPO / "scripts" / "setup.sh"
    r = subprocess.run(["bash", str(script), "--bogus"], capture_output=True, text=True,
                       timeout=30)
    assert r.returncode == 2 and "unknown option" in r.stderr
    # With everything installed, the apt-only mode only checks (no apt-get, no venv).
    r = subprocess.run(["bash", str(script), "--system-only", "--runtime"],
                       capture_output=True, text=True, timeout=60,
                       env={"PATH": "/usr/bin:/bin", "VIEWLOC_SKIP_APT": "1"})
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().endswith("setup: ok (system packages only)")
