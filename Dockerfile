# viewloc service image: one container, data volume at /data, configured only
# through environment variables. The install steps are scripts/setup.sh, the
# same script `make test` runs, so image and CI cannot drift apart.
FROM python:3.11-slim-bookworm

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PYOPENGL_PLATFORM=egl \
    VIEWLOC_DATA_DIR=/data \
    PORT=8000

RUN apt-get update -qq \
    && apt-get install -y -qq --no-install-recommends make curl \
    && rm -rf /var/lib/apt/lists/*

WORKDIR /app
COPY pyproject.toml README.md Makefile ./
COPY scripts ./scripts
COPY viewloc_core ./viewloc_core
COPY model_store ./model_store
COPY app ./app
COPY viewloc_cli ./viewloc_cli
COPY viewloc_client ./viewloc_client
COPY viewloc_bench ./viewloc_bench
RUN bash scripts/setup.sh && rm -rf /var/lib/apt/lists/* /root/.cache/pip

RUN useradd --create-home --uid 10001 viewloc && mkdir -p /data && chown viewloc /data
USER viewloc
VOLUME ["/data"]
EXPOSE 8000
HEALTHCHECK --interval=30s --timeout=5s --start-period=20s \
    CMD curl -fsS "http://127.0.0.1:${PORT}/healthz" || exit 1
CMD ["sh", "-c", ".venv/bin/python -m viewloc_cli serve --host 0.0.0.0 --port ${PORT}"]
