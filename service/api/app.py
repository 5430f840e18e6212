"""The FastAPI application: one job store and one worker per data folder, the routes of
service.api.routes, the page of service.api.page, the error handlers that turn every refusal into a 4xx with a message."""
from __future__ import annotations

import logging
from contextlib import asynccontextmanager
from pathlib import Path
from typing import AsyncIterator

from fastapi import FastAPI
from fastapi.middleware.cors import CORSMiddleware
from fastapi.openapi.utils import get_openapi

from models.pretrained import Networks
from service.api.errors import BodySizeLimit, install_error_handlers
from service.api.metrics import ServiceMetrics
from service.api.page import install_page
from service.api.routes import router
from service.api.schemas import BundleJobCreate, JobCreate, LambdaUpdate
from service.api.security import RequestGuard, SecuritySettings
from service.jobs import bundle
from service.jobs.leases import Leases
from service.jobs.quotas import Quotas
from service.jobs.retention import Housekeeper, Retention
from service.jobs.store import JobStore
from service.jobs.backends import make_worker
from service.jobs.worker_settings import THREADS, WorkerSettings
from service.loop.spec import SERVICE_LIMITS, JobLimits
from service.render.sandbox import wall_support
from service.render.scene_probe import ProbeLimits, SceneProber

log = logging.getLogger(__name__)

FORM_OVERHEAD_BYTES = 1024 * 1024  # multipart headers and the spec field around the bundle
MAX_UPLOAD_BYTES = bundle.MAX_BUNDLE_BYTES + FORM_OVERHEAD_BYTES  # with the default bundle limits


def create_app(data_dir: Path, *, networks: Networks, workers: WorkerSettings = THREADS,
               security: SecuritySettings = SecuritySettings(),
               bundle_limits: bundle.BundleLimits = bundle.BundleLimits(),
               job_limits: JobLimits = SERVICE_LIMITS, retention: Retention = Retention(),
               db_url: str | None = None, quotas: Quotas = Quotas(), leases: Leases = Leases(),
               scene_checks: ProbeLimits = ProbeLimits()) -> FastAPI:
    """`db_url`: None for the SQLite file in `data_dir`, or a postgresql:// URL; job files stay
    under `data_dir` either way. `workers`: the thread backend (default) or Ray."""
    store = JobStore(Path(data_dir), db_url, leases=leases)
    metrics = ServiceMetrics(store)
    worker = make_worker(store, networks, workers, observer=metrics)
    housekeeper = Housekeeper(store, retention)
    prober = SceneProber(scene_checks, preload="service.api.submit")  # uploaded scenes are checked in children

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        wall = wall_support()
        if wall.available:
            log.info("scene files load behind a Landlock wall (ABI %d): the job's folder and installed software only", wall.abi)
        else:
            log.warning("scene files load WITHOUT the kernel wall (%s); the flattener's check is the only wall", wall.reason)
        prober.start()
        worker.start()
        housekeeper.start()
        yield
        housekeeper.stop()
        worker.stop()
        prober.close()

    app = FastAPI(title="renderloop", version="0.1.0", lifespan=lifespan)
    app.state.store, app.state.worker, app.state.metrics = store, worker, metrics
    app.state.bundle_limits, app.state.job_limits = bundle_limits, job_limits
    app.state.scene_prober = prober
    app.state.quotas, app.state.retention = quotas, retention  # POST /jobs: queue and disk caps
    app.add_middleware(BodySizeLimit, max_bytes=bundle_limits.max_bytes + FORM_OVERHEAD_BYTES)
    if security.cors_origins:
        app.add_middleware(CORSMiddleware, allow_origins=list(security.cors_origins), allow_credentials=False,
                           allow_methods=["GET", "POST", "PUT", "DELETE"], allow_headers=["Authorization", "Content-Type"])
    app.add_middleware(RequestGuard, settings=security)  # added last: runs first
    install_error_handlers(app)
    app.include_router(router)
    install_page(app)
    app.openapi = lambda: openapi_document(app)
    return app


def openapi_document(app: FastAPI) -> dict:
    """FastAPI's document plus the request bodies of the routes that read the raw request
    (JSON or multipart), whose schemas it cannot see."""
    if app.openapi_schema is None:
        document = get_openapi(title=app.title, version=app.version, routes=app.routes)
        components = document.setdefault("components", {}).setdefault("schemas", {})
        for model in (JobCreate, BundleJobCreate, LambdaUpdate):
            schema = model.model_json_schema(ref_template="#/components/schemas/{model}")
            components.update(schema.pop("$defs", {}))
            components[model.__name__] = schema
        app.openapi_schema = document
    return app.openapi_schema
