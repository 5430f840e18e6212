"""Turning a POST /jobs request into a stored job: parse strictly, validate with the one job
spec (service/loop/spec.py), unpack a bundle, and check the service's limits on the effective
job — the film size read from the scene when the request gives none."""
from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

from fastapi import Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel, ValidationError
from starlette.datastructures import UploadFile

from service.api.schemas import BundleJobCreate, JobCreate
from service.jobs import bundle
from service.jobs.artifacts import JobFiles
from service.jobs.blobs import BlobStore
from service.loop.budget import fit_iteration_cap, names_a_stopping_rule, rules_as_given, scene_budget
from service.loop.spec import SERVICE_LIMITS, JobLimits, LoopSpec, LoopSpecError, check_limits, job_name
from service.render.scene_probe import ProbeLimitExceeded, SceneProber
from service.render.scenes import SceneError, builtin_scene_names, check_scene, film_size, scene_sample_count

JSON_MEDIA_TYPE = "application/json"


def invalid(location: str, message: str) -> RequestValidationError:
    """A 422 that reads like FastAPI's own."""
    return RequestValidationError([{"loc": (location,), "msg": message}])


def validated(model: type[BaseModel], data: object) -> BaseModel:
    """Pydantic validation whose failure reads like FastAPI's own 422."""
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise RequestValidationError(exc.errors(include_url=False, include_context=False)) from exc


async def json_body(request: Request) -> object:
    try:
        return await request.json()
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError, ValueError) as exc:
        # ValueError: Python refuses integers of thousands of digits; RecursionError: deep nesting.
        raise invalid("body", f"body is not valid JSON ({type(exc).__name__})") from exc


def is_multipart(request: Request) -> bool:
    return request.headers.get("content-type", "").startswith("multipart/form-data")


def uploads(form, name: str) -> list[UploadFile]:
    return [item for item in form.getlist(name) if isinstance(item, UploadFile)]


def require_builtin(scene: str) -> None:
    names = builtin_scene_names()
    if scene not in names:
        raise invalid("scene", f"unknown built-in scene {scene!r}; known: {', '.join(names)} (or upload a bundle)")


def check_effective_job(spec: LoopSpec, root: Path | None = None, limits: JobLimits = SERVICE_LIMITS) -> LoopSpec:
    """Service limits on the job as it will run: the scene's own film size when the request
    names none (a job without width/height must not escape the sample cap). Parsing the scene
    here also turns a broken scene into a 422 at submit instead of a failed job later."""
    try:
        width, height = film_size(spec.scene, width=spec.width, height=spec.height, params=spec.params, root=root,
                                  frames=spec.frames)
        spec = fit_iteration_cap(spec, width, height, limits)  # a time limit alone: the service's cap
        check_limits(spec, width, height, limits)
        if root is not None:  # an uploaded scene: what instantiating it would refuse, refused now
            check_scene(spec.scene, width=spec.width, height=spec.height, params=spec.params, root=root)
    except (SceneError, LoopSpecError) as exc:
        raise invalid("spec", str(exc)) from exc
    return spec


def with_scene_budget(spec: LoopSpec, root: Path) -> LoopSpec:
    """A bundle job that gives no stopping rule: the scene's own sample_count is its budget
    (service/loop/budget.py); built-in scenes keep the default iterations."""
    try:
        return scene_budget(spec, scene_sample_count(spec.scene, params=spec.params, root=root))
    except SceneError as exc:
        raise invalid("spec", str(exc)) from exc


def builtin_job(body: object, limits: JobLimits = SERVICE_LIMITS) -> LoopSpec:
    """The LoopSpec of a JSON request naming a built-in scene, limits checked."""
    request: JobCreate = validated(JobCreate, body)
    require_builtin(request.scene)
    spec = rules_as_given(request.loop_spec(request.scene), request.model_fields_set)
    spec = check_effective_job(spec, None, limits)
    spec.name = job_name(spec)
    return spec


def parse_bundle_spec(raw: object) -> BundleJobCreate:
    try:
        data = json.loads(raw) if isinstance(raw, str) else None
    except (json.JSONDecodeError, RecursionError, ValueError) as exc:
        raise invalid("spec", f"not valid JSON ({type(exc).__name__})") from exc
    return validated(BundleJobCreate, data if data is not None else {})


def unpack_bundle(files: JobFiles, items: list[UploadFile], archive: bool, request: BundleJobCreate,
                  limits: bundle.BundleLimits, job_limits: JobLimits, prober: SceneProber) -> dict:
    """Store the upload under the job's folder and return the stored spec (scene relative to
    the bundle); on any problem the folder is removed and the error propagates. The scene is
    checked in a child process (`prober`), never in the API process; once it passes, the
    bundle's files become links to the shared blobs (one copy of each content on the server)."""
    root = files.bundle_dir.resolve()  # the bundle's checks compare resolved paths
    root.mkdir(parents=True, exist_ok=True)
    try:
        if archive:
            bundle.extract_zip(items[0].file, root, limits)
        else:
            bundle.save_files(((u.filename or "", u.file) for u in items), root, limits)
        stored = checked_in_child(prober, root, request, job_limits)
        BlobStore(files.data_dir).adopt(root)
        return stored
    except BaseException:
        shutil.rmtree(files.root, ignore_errors=True)
        raise


def checked_in_child(prober: SceneProber, root: Path, request: BundleJobCreate, job_limits: JobLimits) -> dict:
    """`check_unpacked` in the scene-check child, its answer raised or returned as if it had
    run here; a check over the child's memory or time limit is a 422 naming the limit."""
    payload = {"root": str(root), "request": request.model_dump_json(exclude_unset=True, by_alias=True),
               "job_limits": dataclasses.asdict(job_limits)}
    try:
        reply = prober.run(check_unpacked, payload, [root])
    except ProbeLimitExceeded as exc:
        raise invalid("bundle", str(exc)) from exc
    if "bundle_error" in reply:
        raise bundle.BundleError(reply["bundle_error"])
    if "invalid" in reply:
        raise RequestValidationError(reply["invalid"])
    return reply["stored"]


def check_unpacked(payload: dict) -> dict:
    """Runs in the scene-check child (service/render/scene_probe.py): the unpacked bundle's
    scene flattened, parsed and loaded, the job's limits checked; answers JSON."""
    request = BundleJobCreate.model_validate_json(payload["request"])
    try:
        return {"stored": stored_bundle_spec(Path(payload["root"]), request, JobLimits(**payload["job_limits"]))}
    except bundle.BundleError as exc:
        return {"bundle_error": str(exc)}
    except RequestValidationError as exc:
        return {"invalid": jsonable_encoder(exc.errors())}


def stored_bundle_spec(root: Path, request: BundleJobCreate, job_limits: JobLimits) -> dict:
    entry = bundle.prepare_bundle(root, request.scene, params=request.params)
    relative = entry.relative_to(root).as_posix()
    spec = request.loop_spec(str(entry))
    if not names_a_stopping_rule(request.model_fields_set):
        spec = with_scene_budget(spec, root)
    spec = check_effective_job(rules_as_given(spec, request.model_fields_set), root, job_limits)
    stored = spec.to_stored()
    stored["scene"] = relative
    stored["name"] = job_name(spec, relative)
    return {**stored, "bundle_scene": relative}
