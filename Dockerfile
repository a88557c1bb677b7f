# viewloc service image (also the worker image: docker-compose.yml runs
# `viewloc worker` from it). Configured only through environment variables
# (.env.example lists them all); the store lives on the /data volume.
#
# Both stages install through scripts/setup.sh, the script `make test` runs:
# the builder builds .venv with it (--python-only), the final stage gets the
# system libraries from the same script's list (--system-only), so the image
# and CI cannot drift apart. --runtime leaves out what only the benchmark and
# the tests need (POV-Ray, redis-server, dev tools).
ARG PYTHON_IMAGE=python:3.11-slim-bookworm

FROM ${PYTHON_IMAGE} AS builder
ENV PYTHONDONTWRITEBYTECODE=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1
WORKDIR /app
COPY pyproject.toml README.md ./
COPY scripts ./scripts
COPY viewloc_core ./viewloc_core
COPY model_store ./model_store
COPY app ./app
COPY viewloc_cli ./viewloc_cli
COPY viewloc_client ./viewloc_client
COPY viewloc_bench ./viewloc_bench
RUN bash scripts/setup.sh --python-only --runtime \
    && find /app -name __pycache__ -prune -exec rm -rf {} +

FROM ${PYTHON_IMAGE}
ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PYOPENGL_PLATFORM=egl \
    VIEWLOC_DATA_DIR=/data \
    HOST=0.0.0.0 \
    PORT=8000 \
    PATH=/app/.venv/bin:$PATH
WORKDIR /app
COPY scripts ./scripts
RUN bash scripts/setup.sh --system-only --runtime \
    && rm -rf /var/lib/apt/lists/*
# The venv was made at /app/.venv on the same base image, so its interpreter
# links and the editable install's paths hold here unchanged.
COPY --from=builder /app /app
RUN useradd --create-home --uid 10001 --user-group viewloc \
    && mkdir -p /data && chown viewloc:viewloc /data
USER viewloc
# numba compiles the pipeline's kernels at start-up and caches them; /app is
# not writable by this user, so the cache lives in its home.
ENV NUMBA_CACHE_DIR=/home/viewloc/.cache/numba
# Compiled now, so a container is ready in seconds (about 35 s of compiling
# otherwise); a host with another CPU compiles its own at start-up.
RUN python -c "from viewloc_core.localize import warm_up; warm_up()"
VOLUME ["/data"]
EXPOSE 8000
# python instead of curl: the slim image has no curl, and one less package.
HEALTHCHECK --interval=30s --timeout=5s --start-period=30s --retries=3 \
    CMD ["python", "-c", "import os, urllib.request; urllib.request.urlopen('http://127.0.0.1:%s/healthz' % os.environ.get('PORT', '8000'), timeout=4)"]
# exec: uvicorn replaces the shell and receives `docker stop`'s SIGTERM itself.
CMD ["sh", "-c", "exec python -m viewloc_cli serve --host \"$HOST\" --port \"$PORT\""]
