"""`renderloop serve`: the API on uvicorn with the job store under a data dir (its SQLite file,
or PostgreSQL with `--db postgresql://…`; job files stay in the data dir).

`app_from_env` is a uvicorn factory (`uvicorn --factory service.api.serve:app_from_env`)
reading RENDERLOOP_DATA_DIR / RENDERLOOP_DB / RENDERLOOP_CONCURRENCY (the thread backend) or
RENDERLOOP_WORKERS / RENDERLOOP_RAY_ADDRESS (Ray, the default) / RENDERLOOP_WEIGHTS_DIR /
RENDERLOOP_TORCH_THREADS / RENDERLOOP_TOKEN / RENDERLOOP_ALLOWED_HOSTS / RENDERLOOP_CORS_ORIGINS /
RENDERLOOP_MAX_QUEUED / RENDERLOOP_MAX_QUEUED_PER_CLIENT / RENDERLOOP_LEASE_SECONDS (the lease only here).
`renderloop serve` (service/cli.py) is the one command line.
"""
from __future__ import annotations

import logging
import os
from dataclasses import replace
from pathlib import Path

import uvicorn
from fastapi import FastAPI

from models.pretrained import Networks, load_networks
from service.api.app import create_app
from service.api.edge import EdgeSettings, uvicorn_options
from service.api.security import SecuritySettings
from service.api.shutdown import sigterm_exits_0
from service.jobs.worker_settings import WorkerSettings
from service.jobs.leases import Leases
from service.jobs.quotas import Quotas
from service.jobs.retention import Retention
from service.jobs.bundle import MAX_BUNDLE_BYTES, MAX_BUNDLE_FILES, BundleLimits
from service.loop.spec import SERVICE_LIMITS, JobLimits
from service.render.runtime import network_device
from service.render.scene_probe import ProbeLimits
from service.loop.tensors import configure_torch_threads

DATA_DIR_ENV = "RENDERLOOP_DATA_DIR"
DB_ENV = "RENDERLOOP_DB"  # a postgresql:// URL; unset or empty: the SQLite file in the data dir
CONCURRENCY_ENV = "RENDERLOOP_CONCURRENCY"  # set: the thread backend with that many threads
WORKERS_ENV = "RENDERLOOP_WORKERS"  # Ray workers on a local runtime (default: one per core)
RAY_ADDRESS_ENV = "RENDERLOOP_RAY_ADDRESS"  # join this Ray cluster
MAX_BUNDLE_MB_ENV = "RENDERLOOP_MAX_BUNDLE_MB"
MAX_BUNDLE_FILES_ENV = "RENDERLOOP_MAX_BUNDLE_FILES"
MAX_JOB_MEMORY_GB_ENV = "RENDERLOOP_MAX_JOB_MEMORY_GB"
KEEP_DAYS_ENV = "RENDERLOOP_KEEP_DAYS"
MAX_DISK_GB_ENV = "RENDERLOOP_MAX_DISK_GB"
DEFAULT_HOST, DEFAULT_PORT = "127.0.0.1", 8000
# On SIGTERM uvicorn waits for open responses before shutting the app down; an event stream
# never ends by itself, so open ones are cut after this grace. Running jobs stop within one
# wavefront chunk and are requeued (service.jobs.worker), so the whole exit takes seconds.
SHUTDOWN_GRACE_SECONDS = 2


def default_data_dir() -> Path:
    return Path(os.environ.get(DATA_DIR_ENV) or "./data")


def bundle_limits_from_env() -> BundleLimits:
    megabytes = os.environ.get(MAX_BUNDLE_MB_ENV)
    files = os.environ.get(MAX_BUNDLE_FILES_ENV)
    return BundleLimits(max_bytes=int(megabytes) * 2**20 if megabytes else MAX_BUNDLE_BYTES,
                        max_files=int(files) if files else MAX_BUNDLE_FILES)


def app_from_env() -> FastAPI:
    configure_torch_threads()
    return create_app(default_data_dir(), networks=load_networks(device=network_device()),
                      workers=worker_settings_from_env(), security=SecuritySettings.from_env(),
                      bundle_limits=bundle_limits_from_env(), job_limits=job_limits_from_env(),
                      retention=retention_from_env(), db_url=os.environ.get(DB_ENV) or None,
                      quotas=Quotas.from_env(), leases=Leases.from_env(), scene_checks=ProbeLimits.from_env())


def worker_settings_from_env() -> WorkerSettings:
    """RENDERLOOP_CONCURRENCY picks the thread backend; otherwise Ray, as `renderloop serve` does."""
    concurrency, workers = os.environ.get(CONCURRENCY_ENV), os.environ.get(WORKERS_ENV)
    if concurrency:
        return WorkerSettings(concurrency=int(concurrency))
    return WorkerSettings(workers=int(workers) if workers else None, ray_address=os.environ.get(RAY_ADDRESS_ENV) or None)


def retention_from_env() -> Retention:
    days, gigabytes = os.environ.get(KEEP_DAYS_ENV), os.environ.get(MAX_DISK_GB_ENV)
    return Retention(keep_days=float(days) if days else None,
                     max_disk_bytes=float(gigabytes) * 2**30 if gigabytes else None)


def job_limits_from_env() -> JobLimits:
    gigabytes = os.environ.get(MAX_JOB_MEMORY_GB_ENV)
    return replace(SERVICE_LIMITS, max_memory_bytes=float(gigabytes) * 2**30) if gigabytes else SERVICE_LIMITS


def serve(host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, data_dir: Path | None = None,
          workers: WorkerSettings = WorkerSettings(), *, networks: Networks, security: SecuritySettings = SecuritySettings(),
          bundle_limits: BundleLimits = BundleLimits(), job_limits: JobLimits = SERVICE_LIMITS,
          retention: Retention = Retention(), db_url: str | None = None, edge: EdgeSettings = EdgeSettings(),
          quotas: Quotas = Quotas(), scene_checks: ProbeLimits = ProbeLimits()) -> None:
    data_dir = Path(data_dir) if data_dir is not None else default_data_dir()
    data_dir.mkdir(parents=True, exist_ok=True)
    app = create_app(data_dir, networks=networks, workers=workers, security=security,
                     bundle_limits=bundle_limits, job_limits=job_limits, retention=retention, db_url=db_url,
                     quotas=quotas, leases=Leases.from_env(), scene_checks=scene_checks)
    log_service_messages()
    with sigterm_exits_0():
        uvicorn.run(app, host=host, port=port, log_level="info", timeout_graceful_shutdown=SHUTDOWN_GRACE_SECONDS,
                    **uvicorn_options(edge))


def log_service_messages() -> None:
    """uvicorn configures only its own loggers; the service's (jobs resumed at start-up, whether
    scene loads are walled) go to stderr beside them, in the same shape."""
    handler = logging.StreamHandler()
    handler.setFormatter(logging.Formatter("%(levelname)s:     %(message)s"))
    logger = logging.getLogger("service")
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
