"""The HTTP API (DESIGN.md, "HTTP"): submit jobs, poll them, fetch previews and results,
change λ, cancel, follow events. Handlers are thin: records live in service.jobs.store,
rendering in service.jobs.worker, bundle checks in service.jobs.bundle."""
from __future__ import annotations

import asyncio
import json
import shutil
from contextlib import asynccontextmanager
from pathlib import Path
from typing import AsyncIterator

import numpy as np
from fastapi import FastAPI, Query, Request, Response
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, StreamingResponse
from pydantic import ValidationError
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import UploadFile

from models.pretrained import Networks
from service.api import imaging
from service.images import png_bytes
from service.api.errors import BodySizeLimit, install_error_handlers
from service.api.lambda_map import constant, decode_map, paint_rects
from service.api.schemas import (
    BundleJobCreate,
    Health,
    ImageFormat,
    JobCreate,
    JobCreated,
    JobList,
    JobStatus,
    LambdaResult,
    LambdaUpdate,
    Layer,
)
from service.jobs import bundle
from service.jobs.errors import JobConflict, JobNotFound
from service.jobs.store import STATES, JobRecord, JobStore
from service.jobs.worker import JobWorker
from service.render.scenes import builtin_scene_names


MAX_UPLOAD_BYTES = bundle.MAX_BUNDLE_BYTES + 1024 * 1024  # the bundle plus form overhead
EVENT_POLL_SECONDS = 0.25
EVENT_KEEPALIVE_SECONDS = 15.0


def _validated(model: type, data: object):
    """Pydantic validation whose failure reads like FastAPI's own 422."""
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise RequestValidationError(exc.errors(include_url=False, include_context=False)) from exc


async def _json_body(request: Request) -> object:
    try:
        return await request.json()
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise RequestValidationError([{"loc": ("body",), "msg": f"body is not valid JSON ({exc})"}]) from exc


def _require_builtin(scene: str) -> None:
    names = builtin_scene_names()
    if scene not in names:
        message = f"unknown built-in scene {scene!r}; known: {', '.join(names)} (or upload a bundle)"
        raise RequestValidationError([{"loc": ("body", "scene"), "msg": message}])


def _is_multipart(request: Request) -> bool:
    return request.headers.get("content-type", "").startswith("multipart/form-data")


def _uploads(form, name: str) -> list[UploadFile]:
    return [item for item in form.getlist(name) if isinstance(item, UploadFile)]


def create_app(data_dir: Path, *, networks: Networks, concurrency: int = 1) -> FastAPI:
    store = JobStore(Path(data_dir))
    worker = JobWorker(store, networks, concurrency=concurrency)

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        worker.start()
        yield
        worker.stop()

    app = FastAPI(title="renderloop", version="0.1.0", lifespan=lifespan)
    app.state.store, app.state.worker = store, worker
    app.add_middleware(BodySizeLimit, max_bytes=MAX_UPLOAD_BYTES)
    install_error_handlers(app)

    def require(job_id: str) -> JobRecord:
        record = store.get(job_id)
        if record is None:
            raise JobNotFound(f"no job with id {job_id!r}")
        return record

    # -- submit ---------------------------------------------------------------------------------

    def unpack_bundle(job_id: str, uploads: list[UploadFile], archive: bool, scene: str | None) -> str:
        root = worker.files(job_id).bundle_dir
        root.mkdir(parents=True, exist_ok=True)
        try:
            if archive:
                bundle.extract_zip(uploads[0].file, root)
            else:
                bundle.save_files(((u.filename or "", u.file) for u in uploads), root)
            entry = bundle.prepare_bundle(root, scene)
        except BaseException:
            shutil.rmtree(root.parent, ignore_errors=True)
            raise
        return entry.relative_to(root.resolve()).as_posix()

    async def create_from_upload(request: Request) -> JobRecord:
        form = await request.form(max_files=bundle.MAX_BUNDLE_FILES + 1, max_fields=8)
        raw_spec = form.get("spec") or "{}"
        try:
            params = json.loads(raw_spec) if isinstance(raw_spec, str) else None
        except json.JSONDecodeError as exc:
            raise RequestValidationError([{"loc": ("spec",), "msg": f"not valid JSON ({exc})"}]) from exc
        spec: BundleJobCreate = _validated(BundleJobCreate, params)
        archives, files = _uploads(form, "bundle"), _uploads(form, "files")
        if bool(archives) == bool(files) or len(archives) > 1:
            raise RequestValidationError(
                [{"loc": ("bundle",), "msg": "upload one zip as 'bundle', or the XML and assets as 'files'"}]
            )
        job_id = store.new_id()
        entry = await run_in_threadpool(unpack_bundle, job_id, archives or files, bool(archives), spec.scene)
        return store.create(spec.stored_spec(bundle_scene=entry), spec.lam, job_id=job_id)

    @app.post("/jobs", status_code=202, response_model=JobCreated)
    async def submit_job(request: Request) -> JobCreated:
        """JSON body naming a built-in scene, or multipart: `spec` (JSON) plus `bundle` (zip)
        or `files` (scene XML and assets, sub-folders in the file names)."""
        if _is_multipart(request):
            record = await create_from_upload(request)
        else:
            spec: JobCreate = _validated(JobCreate, await _json_body(request))
            _require_builtin(spec.scene)
            record = await run_in_threadpool(store.create, spec.stored_spec(), spec.lam)
        worker.submit(record.id)
        return JobCreated(id=record.id, state=record.state)

    # -- read -----------------------------------------------------------------------------------

    @app.get("/jobs", response_model=JobList)
    def list_jobs(
        state: str | None = Query(None, pattern="^(" + "|".join(STATES) + ")$"),
        limit: int = Query(100, ge=1, le=1000),
        offset: int = Query(0, ge=0),
    ) -> JobList:
        return JobList(jobs=[JobStatus.from_record(r) for r in store.list(state, limit, offset)])

    @app.get("/jobs/{job_id}", response_model=JobStatus)
    def get_job(job_id: str) -> JobStatus:
        return JobStatus.from_record(require(job_id))

    @app.get("/jobs/{job_id}/preview")
    def get_preview(
        job_id: str,
        request: Request,
        frame: int = Query(0, ge=0),
        layer: Layer = "denoised",
        format: ImageFormat = "png",
        exposure: float = Query(0.0, ge=-20, le=20, description="stops, radiance layers only"),
    ) -> Response:
        record = require(job_id)
        frames = int(record.spec.get("frames", 1))
        if frame >= frames:
            raise RequestValidationError([{"loc": ("frame",), "msg": f"frame {frame} out of range: the job has {frames}"}])
        preview = worker.files(job_id).load_preview(frame)
        if preview is None:
            return Response(status_code=204)  # no iteration finished yet
        values = preview.layers.get(layer)
        if values is None:
            raise JobConflict(f"layer {layer!r} is not available for this job (no denoiser or error prediction)")
        etag = f'"{preview.version}-{layer}-{format}-{exposure:g}"'
        headers = {"ETag": etag, "X-Preview-Version": str(preview.version), "Cache-Control": "no-cache"}
        if request.headers.get("if-none-match") == etag:
            return Response(status_code=304, headers=headers)
        if format == "exr":
            return Response(imaging.exr_bytes(layer, values), media_type="image/x-exr", headers=headers)
        png = png_bytes(imaging.to_rgb8(layer, values, exposure))
        return Response(png, media_type="image/png", headers=headers)

    @app.get("/jobs/{job_id}/result.exr")
    def get_result(job_id: str, frame: int = Query(0, ge=0)) -> FileResponse:
        record = require(job_id)
        frames = int(record.spec.get("frames", 1))
        if frame >= frames:
            raise RequestValidationError([{"loc": ("frame",), "msg": f"frame {frame} out of range: the job has {frames}"}])
        path = worker.files(job_id).result_path(frame)
        if not record.finished:
            raise JobConflict(f"job is {record.state}: result.exr is written when it finishes")
        if not path.is_file():
            raise JobConflict(f"job is {record.state} and produced no result")
        return FileResponse(path, media_type="image/x-exr", filename=f"{job_id}_frame{frame:03d}.exr")

    # -- change ---------------------------------------------------------------------------------

    def lambda_from_json(job_id: str, update: LambdaUpdate, shape: tuple[int, int]) -> np.ndarray:
        if update.value is not None:
            return constant(shape, update.value)
        return paint_rects(worker.current_lambda(job_id, shape), update.rects or [])

    def apply_lambda(job_id: str, update: LambdaUpdate | None, upload: bytes | None) -> LambdaResult:
        record = require(job_id)
        if record.state in ("failed", "canceled"):
            raise JobConflict(f"job is {record.state}: λ cannot change any more")
        shape = worker.image_size(job_id)
        if shape is None:
            raise JobConflict("the image size is not known before the first iteration; retry once a preview exists")
        lam = decode_map(upload, shape) if upload is not None else lambda_from_json(job_id, update, shape)
        value = update.value if update is not None else None
        applied = worker.set_lambda(job_id, lam, value)
        return LambdaResult(version=applied.version, full_passes=applied.full_passes, tail_passes=applied.tail_passes)

    @app.put("/jobs/{job_id}/lambda", response_model=LambdaResult)
    async def put_lambda(job_id: str, request: Request) -> LambdaResult:
        """JSON `{"value": 2.5}` or `{"rects": [{"x","y","w","h","value"}]}` (painted over the
        current map), or multipart with a single-channel PNG/EXR `map` whose pixels are λ."""
        await run_in_threadpool(require, job_id)
        if _is_multipart(request):
            form = await request.form(max_files=1, max_fields=4)
            maps = _uploads(form, "map")
            if not maps:
                raise RequestValidationError([{"loc": ("map",), "msg": "upload the λ map as form field 'map'"}])
            data = await maps[0].read()
            return await run_in_threadpool(apply_lambda, job_id, None, data)
        update: LambdaUpdate = _validated(LambdaUpdate, await _json_body(request))
        return await run_in_threadpool(apply_lambda, job_id, update, None)

    @app.post("/jobs/{job_id}/cancel", response_model=JobStatus)
    def cancel_job(job_id: str) -> JobStatus:
        return JobStatus.from_record(worker.cancel(job_id))

    # -- follow ---------------------------------------------------------------------------------

    async def event_stream(job_id: str, request: Request) -> AsyncIterator[str]:
        last_sent, quiet = None, 0.0
        while True:
            record = await run_in_threadpool(require, job_id)
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

    @app.get("/jobs/{job_id}/events")
    async def job_events(job_id: str, request: Request) -> StreamingResponse:
        """Server-sent events: `status` on every change of the job record, `end` when it ends."""
        await run_in_threadpool(require, job_id)
        headers = {"Cache-Control": "no-cache", "X-Accel-Buffering": "no"}
        return StreamingResponse(event_stream(job_id, request), media_type="text/event-stream", headers=headers)

    @app.get("/healthz", response_model=Health)
    def health() -> Health:
        counts = {state: len(store.ids_in_state(state)) for state in STATES}
        return Health(status="ok", jobs=counts)

    return app

