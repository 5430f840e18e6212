"""The Python client of the renderloop HTTP API, on httpx.

    from service.client import RenderloopClient

    with RenderloopClient("http://127.0.0.1:8000") as client:    # token: $RENDERLOOP_TOKEN
        job = client.submit("cornell-box", width=64, height=64, max_iterations=3)
        client.wait(job)                                         # a tqdm bar on stderr
        image = client.preview(job)                              # (H, W, 3) float32
        client.download(job, "out.exr")

A scene is a built-in name (GET /scenes) or a local folder / XML file: the files the scene
references (service/scene_upload.py) are zipped and uploaded, nothing else of its folder.
Every refusal raises a RenderloopError carrying the server's status and message; 401, 404, 409
and 422 have their own subclasses.
"""
from __future__ import annotations

import itertools
import json
import os
import sys
import threading
import time
from datetime import datetime
from pathlib import Path
from typing import Any, Iterator

import httpx
import numpy as np
from tqdm import tqdm

from service.api.imaging import EXR_FIELDS
from service.api.security import TOKEN_ENV
from service.atomic import atomic_write
from service.exr import ExrFrame, exr_from_bytes, exr_to_bytes
from service.scene_upload import SceneUpload, plan_upload, zip_upload

SERVER_ENV = "RENDERLOOP_SERVER"
DEFAULT_SERVER = "http://127.0.0.1:8000"
FINISHED_STATES = ("completed", "failed", "canceled")
POLL_SECONDS = 0.5
# The server sends a keep-alive every 15 s on a quiet event stream; four missed ones mean the
# stream is stuck (a buffering proxy): fall back to polling.
EVENT_READ_SECONDS = 60.0


# -- errors -------------------------------------------------------------------------------------

class RenderloopError(Exception):
    """The server refused a request (`status`, its `message`), or could not be reached (status None)."""

    def __init__(self, message: str, status: int | None = None) -> None:
        super().__init__(message if status is None else f"{message} (HTTP {status})")
        self.message = message
        self.status = status


class AuthenticationRequired(RenderloopError):
    """401: the server needs a bearer token (or the one sent is wrong)."""


class NotFound(RenderloopError):
    """404: no such job (or route)."""


class Conflict(RenderloopError):
    """409: the job's state does not allow this now (e.g. the result of a running job)."""


class InvalidRequest(RenderloopError):
    """422: the request is invalid; the message names the field."""


class ServerUnreachable(RenderloopError):
    """No answer from the server at all."""


class JobDidNotComplete(RenderloopError):
    """A job waited for ended failed or canceled (`renderloop submit --wait`)."""


ERROR_TYPES: dict[int, type[RenderloopError]] = {401: AuthenticationRequired, 404: NotFound, 409: Conflict,
                                                 422: InvalidRequest}


def server_message(response: httpx.Response) -> str:
    """The server's `{"detail": …}` message, or the start of whatever else it answered."""
    try:
        detail = response.json().get("detail")
    except (ValueError, AttributeError):
        detail = None
    return str(detail) if detail else (response.text.strip()[:300] or response.reason_phrase)


def raise_for_status(response: httpx.Response) -> httpx.Response:
    if response.is_success:
        return response
    response.read()  # a streamed answer's error body is still unread; a no-op otherwise
    status = response.status_code
    raise ERROR_TYPES.get(status, RenderloopError)(server_message(response), status)


# -- scenes -------------------------------------------------------------------------------------

def is_local_scene(scene: str | os.PathLike) -> bool:
    """A path (uploaded as a bundle) rather than a built-in scene name."""
    text = os.fspath(scene)
    return isinstance(scene, os.PathLike) or Path(text).exists() or "/" in text or text.lower().endswith(".xml")


# -- the client ---------------------------------------------------------------------------------

class RenderloopClient:
    """One server, one connection pool; thread-safe (httpx.Client is)."""

    def __init__(self, server: str | None = None, token: str | None = None, *, timeout: float = 120.0,
                 follow_events: bool = True) -> None:
        """`server` defaults to $RENDERLOOP_SERVER, else http://127.0.0.1:8000; `token` to
        $RENDERLOOP_TOKEN. `follow_events=False` makes `wait` poll instead of following the
        server-sent events."""
        self.server = (server or os.environ.get(SERVER_ENV) or DEFAULT_SERVER).rstrip("/")
        token = token if token is not None else os.environ.get(TOKEN_ENV)
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.follow_events = follow_events
        self._http = httpx.Client(base_url=self.server, headers=headers, timeout=httpx.Timeout(timeout, connect=10.0))
        self._sequence_lock = threading.Lock()
        self._last_sequence = 0

    def __enter__(self) -> "RenderloopClient":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    def _request(self, method: str, path: str, **kwargs) -> httpx.Response:
        try:
            return raise_for_status(self._http.request(method, path, **kwargs))
        except httpx.TransportError as exc:
            raise ServerUnreachable(f"cannot reach {self.server} ({exc.__class__.__name__}: {exc}); "
                                    "is `renderloop serve` running there?") from exc

    # -- jobs ---------------------------------------------------------------------------------

    def submit(self, scene: str | os.PathLike, *, lam: float | None = None, entry: str | None = None,
               **spec: Any) -> str:
        """Start a job; returns its id. `spec` takes the API's fields (width, height, frames,
        max_iterations, spp_budget, time_limit, target_error, allocator, denoise, seed, params,
        spp_first, priority, name); `lam` is λ. A local XML file, or the scene of a folder (`entry`
        picks one when it holds several), is uploaded with only the files it references."""
        if lam is not None:
            spec["lambda"] = lam
        if not is_local_scene(scene):
            return self._request("POST", "/jobs", json={"scene": os.fspath(scene), **spec}).json()["id"]
        upload = plan_upload(scene, scene=entry, params=spec.get("params"), frames=spec.get("frames", 1),
                             width=spec.get("width"), height=spec.get("height"))
        return self.submit_upload(upload, **spec)

    def submit_upload(self, upload: SceneUpload, **spec: Any) -> str:
        """Upload a planned scene (service.scene_upload.plan_upload) as a job; `spec` as in submit
        (with `lambda` under its API name). The job's name defaults to the upload's."""
        with zip_upload(upload) as archive:
            fields = {"spec": json.dumps({"name": upload.name, **spec, "scene": upload.entry})}
            files = {"bundle": ("scene.zip", archive, "application/zip")}
            return self._request("POST", "/jobs", data=fields, files=files).json()["id"]

    def status(self, job_id: str) -> dict:
        return self._request("GET", f"/jobs/{job_id}").json()

    def jobs(self, state: str | None = None, limit: int = 100, offset: int = 0) -> list[dict]:
        """Newest first."""
        params = {"limit": limit, "offset": offset, **({"state": state} if state else {})}
        return self._request("GET", "/jobs", params=params).json()["jobs"]

    def cancel(self, job_id: str) -> dict:
        return self._request("POST", f"/jobs/{job_id}/cancel").json()

    def delete(self, job_id: str) -> None:
        self._request("DELETE", f"/jobs/{job_id}")

    def scenes(self) -> list[dict]:
        return self._request("GET", "/scenes").json()["scenes"]

    def metrics(self) -> str:
        return self._request("GET", "/metrics").text

    # -- waiting ------------------------------------------------------------------------------

    def wait(self, job_id: str, *, progress: bool = True, timeout: float | None = None) -> dict:
        """Block until the job ends and return its final status, with a progress bar on stderr
        unless `progress=False`. Raises TimeoutError after `timeout` seconds (checked at least
        every 15 s)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        status = self.status(job_id)
        bar = tqdm(total=status["spec"].get("max_iterations"), unit="it", desc=job_id[:8], disable=not progress,
                   file=sys.stderr)
        try:
            for status in self._statuses(job_id, status):
                show_progress(bar, status)
                if status["state"] in FINISHED_STATES:
                    return status
                if deadline is not None and time.monotonic() > deadline:
                    raise TimeoutError(f"job {job_id} is still {status['state']} after {timeout:g} s")
        finally:
            bar.close()
        raise AssertionError("unreachable: the polling fallback runs until the job ends")

    def _statuses(self, job_id: str, first: dict) -> Iterator[dict]:
        """Status snapshots until the job ends: the event stream while it works, then polling."""
        yield first
        if first["state"] in FINISHED_STATES:
            return
        if self.follow_events:
            for status in self._events(job_id):
                yield status
                if status["state"] in FINISHED_STATES:
                    return
        while True:  # no events (a proxy that buffers them, an old server), or the stream broke
            status = self.status(job_id)
            yield status
            if status["state"] in FINISHED_STATES:
                return
            time.sleep(POLL_SECONDS)

    def _events(self, job_id: str) -> Iterator[dict]:
        """`status` events of GET /jobs/{id}/events (each keep-alive yields the last one again,
        so the caller can check its deadline); ends quietly when the stream is unusable."""
        timeout = httpx.Timeout(EVENT_READ_SECONDS, connect=10.0)
        last: dict | None = None
        try:
            with self._http.stream("GET", f"/jobs/{job_id}/events", timeout=timeout) as response:
                if response.status_code != 200 or "text/event-stream" not in response.headers.get("content-type", ""):
                    return
                for kind, data in parse_events(response.iter_lines()):
                    if kind == "status":
                        last = json.loads(data)
                        yield last
                    elif kind == "keep-alive" and last is not None:
                        yield last
                    elif kind == "end":
                        return
        except (httpx.TransportError, json.JSONDecodeError):
            return

    # -- images -------------------------------------------------------------------------------

    def preview(self, job_id: str, layer: str = "denoised", frame: int = 0) -> np.ndarray | None:
        """The newest preview layer as float values: denoised/noisy (H, W, 3); error, spp,
        lambda (H, W). None before the first iteration has finished."""
        if layer not in EXR_FIELDS:
            raise ValueError(f"unknown preview layer {layer!r}; choose one of {', '.join(EXR_FIELDS)}")
        response = self._request("GET", f"/jobs/{job_id}/preview",
                                 params={"layer": layer, "format": "exr", "frame": frame})
        if response.status_code == 204:
            return None
        return getattr(exr_from_bytes(response.content), EXR_FIELDS[layer])

    def download(self, job_id: str, path: str | os.PathLike, frame: int = 0) -> Path:
        """The finished job's multi-layer EXR of `frame`, written to `path` (whole or not at all)."""
        def write(tmp: Path) -> None:
            try:
                with self._http.stream("GET", f"/jobs/{job_id}/result.exr", params={"frame": frame}) as response:
                    raise_for_status(response)
                    with open(tmp, "wb") as out:
                        for chunk in response.iter_bytes():
                            out.write(chunk)
            except httpx.TransportError as exc:
                raise ServerUnreachable(f"download from {self.server} broke off ({exc})") from exc

        return atomic_write(path, write)

    # -- λ ------------------------------------------------------------------------------------

    def set_lambda(self, job_id: str, value: float | None = None, *, rects: list | None = None,
                   lambda_map: np.ndarray | None = None, sequence: int | None = None) -> dict:
        """Give exactly one: a global λ `value`; `rects`, painted over the current map — dicts
        with x, y, w, h, value or (x, y, w, h, value) tuples; or a per-pixel (H, W) `lambda_map`
        (sent as an EXR). Returns the server's {version, full_passes, tail_passes}.

        Each edit carries a sequence number taken when it is called (or `sequence`), so edits
        from several threads end on the one issued last even when they overtake each other."""
        if sum(x is not None for x in (value, rects, lambda_map)) != 1:
            raise ValueError("give exactly one of value, rects or lambda_map")
        sequence = self._next_sequence() if sequence is None else sequence
        path = f"/jobs/{job_id}/lambda"
        if lambda_map is not None:
            lam = np.asarray(lambda_map, dtype=np.float32)
            if lam.ndim != 2:
                raise ValueError(f"lambda_map must be (H, W), got shape {lam.shape}")
            data = exr_to_bytes(ExrFrame(lam=lam, header={"layer": "lambda"}))
            files = {"map": ("lambda.exr", data, "image/x-exr")}
            return self._request("PUT", path, files=files, data={"sequence": str(sequence)}).json()
        body: dict[str, Any] = {"value": float(value)} if value is not None else {"rects": [as_rect(r) for r in rects]}
        return self._request("PUT", path, json={**body, "sequence": sequence}).json()

    def _next_sequence(self) -> int:
        # Milliseconds since the epoch (what the API documents), strictly increasing within this
        # client: another client (or this one after a restart) that edits the same job later
        # still counts as newer.
        with self._sequence_lock:
            self._last_sequence = max(self._last_sequence + 1, time.time_ns() // 1_000_000)
            return self._last_sequence


def as_rect(rect: dict | tuple | list) -> dict:
    if isinstance(rect, dict):
        return rect
    x, y, w, h, value = rect
    return {"x": int(x), "y": int(y), "w": int(w), "h": int(h), "value": float(value)}


def parse_events(lines: Iterator[str]) -> Iterator[tuple[str, str]]:
    """(event name, data) of a server-sent event stream; comments come out as ("keep-alive", "")."""
    kind, data = "message", []
    for line in itertools.chain(lines, [""]):
        if line.startswith(":"):
            yield "keep-alive", ""
        elif line.startswith("event:"):
            kind = line[len("event:"):].strip()
        elif line.startswith("data:"):
            data.append(line[len("data:"):].strip())
        elif not line and data:
            yield kind, "\n".join(data)
            kind, data = "message", []


# tqdm's own "remaining" extrapolates the mean time per iteration, but each iteration doubles the
# samples ("7 s left", 18 s in fact): the bar shows the server's ETA (service/loop/eta.py) instead.
PROGRESS_FORMAT = "{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} [{elapsed}{postfix}]"


def seconds_left(status: dict) -> float | None:
    """The server's ETA counted down to now: from its predicted end when it sent one."""
    finish_at = status.get("eta_finish_at")
    if finish_at:
        return max(0.0, datetime.fromisoformat(finish_at).timestamp() - time.time())
    return status.get("eta_seconds")


def show_progress(bar: tqdm, status: dict) -> None:
    bar.bar_format = PROGRESS_FORMAT
    error, left = status.get("predicted_error"), seconds_left(status)
    bar.set_postfix(state=status["state"], spp=f"{status['spp']:.1f}",
                    error="-" if error is None else f"{error:.4f}",
                    left="?" if left is None else f"{left:.0f}s", refresh=False)
    bar.update(max(0, status["iteration"] - bar.n))
