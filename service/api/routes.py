"""The HTTP routes (docs/design.md, "Contracts"): submit jobs, poll them, fetch previews and results,
change λ, cancel, follow events. Handlers are thin: records live in service.jobs.store,
rendering in service.jobs.worker, bundle checks in service.jobs.bundle, request parsing in
service.api.submit. The store and worker reach handlers as dependencies."""
from __future__ import annotations

import asyncio
import json
import time
from functools import lru_cache
from typing import Annotated, AsyncIterator

import numpy as np
from fastapi import APIRouter, Depends, HTTPException, Query, Request, Response
from fastapi.responses import FileResponse, StreamingResponse
from starlette.concurrency import run_in_threadpool

from service.api import imaging
from service.api.admission import admit, check_disk, create_job, discard, idempotency_key, submitter
from service.api.metrics import MEDIA_TYPE as METRICS_MEDIA_TYPE, ServiceMetrics
from service.api.lambda_map import constant, decode_map, paint_rects
from service.api.links import JobLinks, job_links, request_signer
from service.api.server_info import ServerInfo, server_info
from service.api.server_timing import HEADER as SERVER_TIMING, server_timing
from service.jobs.blobs import BlobStore
from service.api.schemas import (ErrorBody, Health, ImageFormat, JobCreate, JobCreated, JobList, JobStatus,
                                 LambdaResult, LambdaUpdate, Layer, MAX_SEQUENCE, SEQUENCE_DESCRIPTION, SceneInfo,
                                 SceneList)
from service.api.submit import (builtin_job, invalid, is_multipart, json_body, parse_bundle_spec, unpack_bundle,
                                uploads, validated)
from service.jobs import bundle
from service.jobs.errors import JobConflict, JobNotFound
from service.jobs.record import job_spec
from service.jobs.store import CANCELED, FAILED, STATES, JobRecord, JobStore
from service.jobs.runner import JobRunner
from service.render.effects import inspect_scene
from service.render.scenes import describe_builtin_scenes, film_size

EVENT_POLL_SECONDS = 0.25
EVENT_KEEPALIVE_SECONDS = 15.0
MAX_OFFSET = 2**62  # SQLite integers are 64-bit: larger offsets cannot name a row anyway

def _error(description: str) -> dict:
    return {"model": ErrorBody, "description": description}


# What any route may answer besides its success (OpenAPI; every one carries ErrorBody).
COMMON_ERRORS = {
    400: _error("the Host header is not served here"),
    401: _error("the server needs a bearer token"),
    403: _error("a browser request from another web origin may not change anything"),
    413: _error("the request body is over the upload cap"),
    415: _error("a body that is neither application/json nor multipart/form-data"),
    422: _error("invalid input; the message names the field"),
}
JOB_ERRORS = {404: _error("no job with this id"), 409: _error("the job's state does not allow this now")}
router = APIRouter(responses=COMMON_ERRORS)


def _json_or_multipart(json_model: type, multipart: dict) -> dict:
    """An OpenAPI request body for routes that read the raw request (JSON or an upload)."""
    return {"requestBody": {"required": True, "content": {
        "application/json": {"schema": {"$ref": f"#/components/schemas/{json_model.__name__}"}},
        "multipart/form-data": {"schema": multipart}}}}


SUBMIT_BODY = _json_or_multipart(JobCreate, {
    "type": "object", "required": ["spec"], "properties": {
        "spec": {"type": "string", "description": "BundleJobCreate as JSON (scene: the XML inside the bundle)"},
        "bundle": {"type": "string", "format": "binary", "description": "a zip of the scene folder"},
        "files": {"type": "array", "items": {"type": "string", "format": "binary"},
                  "description": "or the XML and its assets, sub-folders in the file names"}}})
LAMBDA_BODY = _json_or_multipart(LambdaUpdate, {
    "type": "object", "required": ["map"], "properties": {
        "map": {"type": "string", "format": "binary", "description": "single-channel PNG/EXR whose pixels are λ"},
        "sequence": {"type": "integer", "minimum": 0, "maximum": MAX_SEQUENCE, "description": SEQUENCE_DESCRIPTION}}})


def get_store(request: Request) -> JobStore:
    return request.app.state.store


def get_worker(request: Request) -> JobRunner:
    return request.app.state.worker


def get_metrics(request: Request) -> ServiceMetrics:
    return request.app.state.metrics


Store = Annotated[JobStore, Depends(get_store)]
Worker = Annotated[JobRunner, Depends(get_worker)]


def require_job(store: JobStore, job_id: str) -> JobRecord:
    record = store.get(job_id)
    if record is None:
        raise JobNotFound(f"no job with id {job_id!r}")
    return record


def job_record(job_id: str, store: Store) -> JobRecord:
    return require_job(store, job_id)


Job = Annotated[JobRecord, Depends(job_record)]


def check_frame(record: JobRecord, frame: int) -> None:
    frames = job_spec(record).frames
    if frame >= frames:
        raise invalid("frame", f"frame {frame} out of range: the job has {frames}")


# -- submit -----------------------------------------------------------------------------------

@router.post("/jobs", status_code=202, response_model=JobCreated, openapi_extra=SUBMIT_BODY, responses={
    200: {"model": JobCreated, "description": "this Idempotency-Key was used before: the job it created"},
    429: _error("the queue is full, for the server or for this client (see Retry-After)"),
    507: _error("the data folder is at its cap (--max-disk-gb)")})
async def submit_job(request: Request, response: Response, store: Store, worker: Worker) -> JobCreated:
    """JSON body naming a built-in scene, or multipart: `spec` (JSON) plus `bundle` (zip)
    or `files` (scene XML and assets, sub-folders in the file names). An `Idempotency-Key`
    header makes a retry safe: the same key (and client) gives back the first job."""
    client, key = submitter(request), idempotency_key(request)
    first = await run_in_threadpool(store.find_submitted, client, key)
    if first is not None:
        response.status_code = 200
        return JobCreated(id=first.id, state=first.state)
    await run_in_threadpool(admit, store, request, client)
    if is_multipart(request):
        limits: bundle.BundleLimits = request.app.state.bundle_limits
        form = await request.form(max_files=limits.max_files + 1, max_fields=8)
        spec_request = parse_bundle_spec(form.get("spec") or "{}")
        archives, files = uploads(form, "bundle"), uploads(form, "files")
        if bool(archives) == bool(files) or len(archives) > 1:
            raise invalid("bundle", "upload one zip as 'bundle', or the XML and assets as 'files'")
        job_id = store.new_id()
        stored = await run_in_threadpool(unpack_bundle, worker.files(job_id), archives or files, bool(archives),
                                         spec_request, limits, request.app.state.job_limits,
                                         request.app.state.scene_prober)
        try:
            await run_in_threadpool(check_disk, store, request)
        except HTTPException:
            discard(store, job_id)
            raise
        record, created = await run_in_threadpool(create_job, store, request, stored, stored["lambda"], client, key,
                                                  job_id)
    else:
        spec = await run_in_threadpool(builtin_job, await json_body(request), request.app.state.job_limits)
        record, created = await run_in_threadpool(create_job, store, request, spec.to_stored(), spec.lam, client, key)
    if not created:
        response.status_code = 200
        return JobCreated(id=record.id, state=record.state)
    worker.submit(record.id)
    return JobCreated(id=record.id, state=record.state)


# -- read ---------------------------------------------------------------------------------------

@router.get("/jobs", response_model=JobList)
def list_jobs(
    store: Store,
    state: str | None = Query(None, pattern="^(" + "|".join(STATES) + ")$"),
    limit: int = Query(100, ge=1, le=1000),
    offset: int = Query(0, ge=0, le=MAX_OFFSET),
) -> JobList:
    return JobList(jobs=[JobStatus.from_record(r) for r in store.list(state, limit, offset)])


@router.get("/jobs/{job_id}", response_model=JobStatus, responses=JOB_ERRORS)
def get_job(record: Job) -> JobStatus:
    return JobStatus.from_record(record)


@router.get("/jobs/{job_id}/preview", responses={
    **JOB_ERRORS,
    200: {"content": {"image/png": {}, "image/x-exr": {}}, "description": "the layer, with an ETag"},
    204: {"description": "no iteration has finished yet"},
    304: {"description": "unchanged since the ETag sent in If-None-Match"}})
def get_preview(
    record: Job,
    worker: Worker,
    request: Request,
    frame: int = Query(0, ge=0),
    layer: Layer = "denoised",
    format: ImageFormat = "png",
    exposure: float = Query(0.0, ge=-20, le=20, description="stops, radiance layers only"),
) -> Response:
    check_frame(record, frame)
    preview = worker.load_preview(record.id, frame)  # a λ edit's from memory until its files land
    if preview is None:
        return Response(status_code=204)  # no iteration finished yet
    values = preview.layers.get(layer)
    if values is None:
        raise JobConflict(f"layer {layer!r} is not available for this job (no denoiser or error prediction)")
    etag = f'"{preview.version}-{layer}-{format}-{exposure:g}"'
    headers = {"ETag": etag, "X-Preview-Version": str(preview.version), "Cache-Control": "no-cache"}
    if request.headers.get("if-none-match") == etag:
        return Response(status_code=304, headers=headers)
    started = time.perf_counter()
    if format == "exr":
        body, media_type = imaging.exr_bytes(layer, values), "image/x-exr"
    else:
        body, media_type = imaging.png_preview(layer, values, exposure), "image/png"
    headers[SERVER_TIMING] = server_timing({"encode": time.perf_counter() - started})
    return Response(body, media_type=media_type, headers=headers)


@router.get("/jobs/{job_id}/result.exr", responses={
    **JOB_ERRORS, 200: {"content": {"image/x-exr": {}}, "description": "the frame's multi-layer EXR"}})
def get_result(record: Job, worker: Worker, frame: int = Query(0, ge=0)) -> FileResponse:
    check_frame(record, frame)
    if not record.finished:
        raise JobConflict(f"job is {record.state}: result.exr is written when it finishes")
    started = time.perf_counter()
    path = worker.result_path(record.id, frame)  # the job's λ edits written into it first
    if not path.is_file():
        raise JobConflict(f"job is {record.state} and produced no result")
    return FileResponse(path, media_type="image/x-exr", filename=f"{record.id}_frame{frame:03d}.exr",
                        headers={SERVER_TIMING: server_timing({"flush": time.perf_counter() - started})})


# -- change -------------------------------------------------------------------------------------

def lambda_from_json(worker: JobRunner, job_id: str, update: LambdaUpdate, shape: tuple[int, int]) -> np.ndarray:
    if update.value is not None:
        return constant(shape, update.value)
    return paint_rects(worker.current_lambda(job_id, shape), update.rects or [])


def apply_lambda(store: JobStore, worker: JobRunner, job_id: str, update: LambdaUpdate | None,
                 upload: bytes | None, sequence: int | None = None) -> Response:
    """The edit's LambdaResult, with the parts it took in a Server-Timing header (seconds →
    ms: "map" the λ map built from the request, then LambdaApplied.timings, "total" all of it)."""
    started = time.perf_counter()
    record = require_job(store, job_id)
    if record.state in (FAILED, CANCELED):
        raise JobConflict(f"job is {record.state}: λ cannot change any more")
    shape = worker.image_size(job_id)
    if shape is None:
        raise JobConflict("the image size is not known before the first iteration; retry once a preview exists")
    lam = decode_map(upload, shape) if upload is not None else lambda_from_json(worker, job_id, update, shape)
    if update is not None:
        sequence = update.sequence
    built = time.perf_counter()
    applied = worker.set_lambda(job_id, lam, update.value if update is not None else None, sequence)
    timings = {"map": built - started, **applied.timings, "total": time.perf_counter() - started}
    result = LambdaResult(version=applied.version, full_passes=applied.full_passes, tail_passes=applied.tail_passes)
    return Response(result.model_dump_json(), media_type="application/json", headers={SERVER_TIMING: server_timing(timings)})


def form_sequence(raw: object) -> int | None:
    """The optional `sequence` form field of a map upload, checked like the JSON field."""
    if raw is None:
        return None
    if not isinstance(raw, str) or not raw.isdigit() or int(raw) > MAX_SEQUENCE:
        raise invalid("sequence", f"must be an integer in [0, {MAX_SEQUENCE}]")
    return int(raw)


@router.put("/jobs/{job_id}/lambda", response_model=LambdaResult, responses=JOB_ERRORS, openapi_extra=LAMBDA_BODY)
async def put_lambda(job_id: str, request: Request, store: Store, worker: Worker) -> Response:
    """JSON `{"value": 2.5}` or `{"rects": [{"x","y","w","h","value"}]}` (painted over the
    current map), or multipart with a single-channel PNG/EXR `map` whose pixels are λ. An
    optional `sequence` orders one client's edits (see LambdaUpdate)."""
    await run_in_threadpool(require_job, store, job_id)
    if is_multipart(request):
        form = await request.form(max_files=1, max_fields=4)
        maps = uploads(form, "map")
        if not maps:
            raise invalid("map", "upload the λ map as form field 'map'")
        sequence = form_sequence(form.get("sequence"))
        data = await maps[0].read()
        return await run_in_threadpool(apply_lambda, store, worker, job_id, None, data, sequence)
    update: LambdaUpdate = validated(LambdaUpdate, await json_body(request))
    return await run_in_threadpool(apply_lambda, store, worker, job_id, update, None)


@router.delete("/jobs/{job_id}", status_code=204, responses=JOB_ERRORS)
def delete_job(job_id: str, store: Store, worker: Worker) -> Response:
    """Cancel the job if it is still queued or running, then remove its record and files (and
    the uploaded files no other job shares: service/jobs/blobs.py)."""
    worker.delete(job_id)
    BlobStore(store.data_dir).release_unused()
    return Response(status_code=204)


@router.post("/jobs/{job_id}/cancel", response_model=JobStatus, responses=JOB_ERRORS)
def cancel_job(job_id: str, worker: Worker) -> JobStatus:
    return JobStatus.from_record(worker.cancel(job_id))


# -- follow -------------------------------------------------------------------------------------

async def event_stream(store: JobStore, job_id: str, request: Request) -> AsyncIterator[str]:
    last_sent, quiet = None, 0.0
    while True:
        record = await run_in_threadpool(require_job, store, job_id)
        status = JobStatus.from_record(record).model_dump(mode="json")
        if status != last_sent:
            yield f"event: status\ndata: {json.dumps(status)}\n\n"
            last_sent, quiet = status, 0.0
        if record.finished:
            yield f"event: end\ndata: {json.dumps({'id': job_id, 'state': record.state})}\n\n"
            return
        if quiet >= EVENT_KEEPALIVE_SECONDS:
            yield ": keep-alive\n\n"  # proxies drop silent connections
            quiet = 0.0
        if await request.is_disconnected():
            return
        await asyncio.sleep(EVENT_POLL_SECONDS)
        quiet += EVENT_POLL_SECONDS


@router.get("/jobs/{job_id}/events", responses={
    **JOB_ERRORS, 200: {"content": {"text/event-stream": {}}, "description": "status events until the job ends"},
    429: _error("this client has its most event streams open (serve --max-event-streams)"),
    503: _error("the server has its most event streams open")})
async def job_events(job_id: str, request: Request, store: Store) -> StreamingResponse:
    """Server-sent events: `status` on every change of the job record, `end` when it ends."""
    await run_in_threadpool(require_job, store, job_id)
    headers = {"Cache-Control": "no-cache", "X-Accel-Buffering": "no"}
    return StreamingResponse(event_stream(store, job_id, request), media_type="text/event-stream", headers=headers)


@router.get("/jobs/{job_id}/links", response_model=JobLinks, responses=JOB_ERRORS)
def get_links(record: Job, request: Request) -> JobLinks:
    """URLs of the job's preview and event stream for elements that cannot send the token
    (`<img>`, EventSource): signed, valid for a few minutes, when the server has a token. The
    token itself is not accepted in a URL."""
    return job_links(record.id, request_signer(request))


@lru_cache(maxsize=1)
def builtin_scene_list() -> SceneList:
    """Every built-in scene with its film size and effects report (loaded once per process)."""
    scenes = []
    for name, description in describe_builtin_scenes():
        width, height = film_size(name)
        scenes.append(SceneInfo(name=name, description=description, width=width, height=height,
                                effects=inspect_scene(name).as_record()))
    return SceneList(scenes=scenes)


@router.get("/scenes", response_model=SceneList)
def list_scenes() -> SceneList:
    """The built-in scenes a JSON job may name, with what each calls for."""
    return builtin_scene_list()


@router.get("/info", response_model=ServerInfo)
def get_info(worker: Worker) -> ServerInfo:
    """What renders this server's jobs: CPU or GPU, the Mitsuba variant, the backend."""
    return server_info(worker)


@router.get("/metrics", response_class=Response, responses={
    200: {"content": {"text/plain": {"schema": {"type": "string"}}},
          "description": "Prometheus text format: renderloop_jobs{state}, renderloop_iteration_stage_seconds{stage}, "
                         "renderloop_lambda_edit_seconds, renderloop_samples_rendered_total, "
                         "renderloop_iterations_total"}})
def metrics(service_metrics: Annotated[ServiceMetrics, Depends(get_metrics)]) -> Response:
    """Prometheus metrics of this server (needs the bearer token when one is set)."""
    return Response(service_metrics.exposition(), media_type=METRICS_MEDIA_TYPE)


@router.get("/healthz", response_model=Health, responses={503: {"model": Health, "description": "no job can run"}})
def health(store: Store, worker: Worker, response: Response) -> Health:
    """200 when jobs can run; 503 with a message when they cannot (the backend is down or stopping)."""
    problem = worker.health_problem()
    if problem is not None:
        response.status_code = 503
    return Health(status="unavailable" if problem else "ok", message=problem,
                  jobs={state: len(store.ids_in_state(state)) for state in STATES})
