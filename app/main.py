"""Application factory: settings are read when the app is built, never at import."""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator, Callable, Mapping
from contextlib import asynccontextmanager

from fastapi import Depends, FastAPI

from app.deps import require_api_key
from app.jobs.factory import build_runner
from app.model_warmer import ModelWarmer
from app.observability import Metrics, ServiceMiddleware, configure_logging
from app.openapi_doc import install_openapi
from app.paths import EmptySegmentGuard
from app.problems import install_fallback_handler, install_problem_handlers
from app.routers import jobs, localize, objects, ops
from app.settings import Settings
from model_store import ModelStore
from viewloc_core.localize import prepare as localize_prepare
from viewloc_core.localize import warm_up as localize_warm_up

log = logging.getLogger("viewloc.app")

_DESCRIPTION = """\
View-based 6D localization of rigid parts from single images (Plagemann, Müller,
Burgard, DAGM 2005). Learn an object from a CAD mesh or from images, then
localize it: pose = object -> camera (`x_cam = R x_obj + t`), OpenCV camera frame,
millimetres, degrees, quaternions `[w, x, y, z]`. Errors are
`application/problem+json` (RFC 9457). When `VIEWLOC_API_KEYS` is set, every
endpoint but `/healthz` needs `Authorization: Bearer <key>`.
"""


def _body_limit(settings: Settings) -> Callable[[str], int]:
    small = 1024 * 1024

    def limit(path: str) -> int:
        if path == "/v1/objects":
            return settings.max_mesh_bytes + small
        if path == "/v1/objects/from-images":
            return settings.max_images_total_bytes
        if path.endswith("/localize"):
            return settings.max_image_bytes + small
        return small

    return limit


def create_app(
    settings: Settings | None = None, tasks: Mapping[str, str] | None = None
) -> FastAPI:
    """Build the viewloc FastAPI application.

    Parameters
    ----------
    settings : Settings, optional
        Configuration; read from ``VIEWLOC_*`` environment variables when None.
    tasks : mapping, optional
        Extra job kinds for the job runner ("kind" -> "module:function").
    """
    settings = settings or Settings()
    configure_logging(settings.log_level, settings.log_json)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        # Compiled kernels first: the first localization must not wait for them.
        localize_warm_up()
        store = ModelStore(settings.data_dir, cache_size=settings.model_cache_size)
        runner = build_runner(store, settings, tasks)
        runner.start()
        warmer = ModelWarmer(store, localize_prepare,
                             settings.model_cache_size if settings.prepare_models else 0)
        warmer.start()
        app.state.store, app.state.runner, app.state.warmer = store, runner, warmer
        log.info("viewloc serving store %s with %s job runner", store.root,
                 settings.job_backend)
        try:
            yield
        finally:
            app.state.runner = app.state.warmer = None
            warmer.stop()
            runner.stop()

    application = FastAPI(
        title="viewloc", version="1.0.0", description=_DESCRIPTION, lifespan=lifespan,
        # Starlette refuses more than 1000 files with a bare 400 before a route
        # runs; from-images may carry max_images images and as many masks, and
        # its own limit answers 413 naming the field.
        form_limits={"max_files": max(1000, 2 * settings.max_images + 1)},
    )
    application.state.settings = settings
    application.state.store = None
    application.state.runner = None
    application.state.warmer = None
    metrics = Metrics(lambda: application.state.store.job_counts()
                      if application.state.store is not None else {})
    application.state.metrics = metrics

    auth = [Depends(require_api_key)]
    application.include_router(ops.public_router)
    for router in (ops.router, objects.router, jobs.router, localize.router):
        application.include_router(router, dependencies=auth)

    install_problem_handlers(application)
    install_fallback_handler(application)
    install_openapi(application)
    # Inside the service middleware, which gives its answer a request id and
    # logs it.
    application.add_middleware(EmptySegmentGuard)
    application.add_middleware(ServiceMiddleware, metrics=metrics,
                               body_limit=_body_limit(settings))
    return application

