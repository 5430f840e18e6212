"""A real uvicorn server in a subprocess, and the λ-over-HTTP latency measured against it.

The server is exactly `service.api.serve.app_from_env`, so the figure includes routing, JSON,
the job store and the cached λ tail: what a user sees. Each edit is a PUT and the GET of the
preview it made (what the page does); the server's Server-Timing headers split both into
EDIT_PARTS.
"""
from __future__ import annotations

import math
import os
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import httpx
import numpy as np
import uvicorn

from bench.preview_encoding import time_preview_encoding
from models.pretrained import WEIGHTS_DIR_ENV
from service.api.serve import DATA_DIR_ENV, app_from_env
from service.api.server_timing import HEADER as SERVER_TIMING, parse_server_timing
from service.exr import exr_from_bytes
from service.loop.tensors import TORCH_THREADS_ENV

SERVER_STARTUP_SECONDS = 180.0  # importing torch + Mitsuba on a loaded 2-core machine is slow
FINISHED_STATES = ("completed", "failed", "canceled")


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def serve_for_bench(port: int, data_dir: str, weights_dir: str, torch_threads: int) -> None:
    """Server subprocess entry: exactly `service.api.serve.app_from_env` on uvicorn, with the
    default weights pointed at `weights_dir` (a bench or test may run on other weights)."""
    os.environ[TORCH_THREADS_ENV] = str(torch_threads)  # app_from_env pins them from it
    os.environ[WEIGHTS_DIR_ENV] = weights_dir
    os.environ[DATA_DIR_ENV] = data_dir
    uvicorn.run(app_from_env(), host="127.0.0.1", port=port, log_level="warning")


@contextmanager
def running_server(data_dir: Path, weights_dir: Path, torch_threads: int = 1) -> Iterator[str]:
    """A real uvicorn server on a free local port in a subprocess; yields its base URL."""

    data_dir.mkdir(parents=True, exist_ok=True)
    port = free_port()
    code = (f"from bench.server import serve_for_bench; "
            f"serve_for_bench({port}, {str(data_dir)!r}, {str(weights_dir)!r}, {torch_threads})")
    log = open(data_dir / "server.log", "ab")
    process = subprocess.Popen([sys.executable, "-c", code], stdout=log, stderr=subprocess.STDOUT,
                               env={**os.environ, "PYTHONUNBUFFERED": "1"})
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + SERVER_STARTUP_SECONDS
        while True:
            if process.poll() is not None:
                raise RuntimeError(f"server exited early: {(data_dir / 'server.log').read_text()[-2000:]}")
            try:
                if httpx.get(url + "/healthz", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError(f"server did not come up in {SERVER_STARTUP_SECONDS:.0f} s")
            time.sleep(0.3)
        yield url
    finally:
        process.terminate()
        try:
            process.wait(30)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(10)
        log.close()


def wait_for_job(client, job_id: str, timeout: float = 600.0) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job = client.get(f"/jobs/{job_id}").json()
        if job["state"] in FINISHED_STATES:
            return job
        time.sleep(0.1)
    raise TimeoutError(f"job {job_id} did not finish in {timeout:.0f} s")


# The parts of one edit, in the order a request meets them (keys of `EditTiming.parts`):
# the server's own from its Server-Timing headers (service/api/routes.py, LambdaApplied.timings).
EDIT_PARTS = (
    ("http", "HTTP, routing, JSON (the PUT's round trip less the server's handling)"),
    ("map", "λ map built from the request (a painted one over the saved map)"),
    ("save", "λ map saved (the edit's durable record) + job store"),
    ("tail", "the λ tail where the loop lives (Denoiser.apply from cached features, images out)"),
    ("final", "the final image (converged pixels kept, the blend toward the raw image)"),
    ("hop", "Ray: the actor calls beyond the actor's re-denoise (λ map in, images out through the object store)"),
    ("publish", "new preview version published in memory"),
    ("other", "the rest of the server's handling (the λ mailbox's hand-over, finding the job's loop)"),
    ("encode", "GET preview: the layer tonemapped and PNG-encoded"),
    ("transfer", "GET preview: the rest (HTTP, the PNG's bytes)"),
)


@dataclass
class EditTiming:
    """One λ edit as the page sees it: PUT /jobs/{id}/lambda, then GET of the denoised preview
    (PNG, as the page reloads it) at the version the PUT answered."""

    put_s: float
    get_s: float
    parts: dict[str, float]  # seconds by EDIT_PARTS key
    changed: bool  # the preview's bytes differ from the edit's before

    @property
    def readable_s(self) -> float:
        return self.put_s + self.get_s


def edit_parts(put_s: float, get_s: float, put_timing: dict[str, float], get_timing: dict[str, float]) -> dict[str, float]:
    """EDIT_PARTS from the client's wall times and the server's timings (seconds). They add up to
    the round trip: "http" is the PUT beyond the server's "total", "other" the server's total
    beyond its named parts, "transfer" the GET beyond its "encode"."""
    named = ("map", "save", "tail", "hop", "publish")
    parts = {key: put_timing.get(key, 0.0) for key in named}
    parts["final"] = put_timing.get("denoise", 0.0) - parts["tail"]
    return {"http": put_s - put_timing.get("total", 0.0), **parts,
            "other": put_timing.get("total", 0.0) - sum(parts.values()),
            "encode": get_timing.get("encode", 0.0), "transfer": get_s - get_timing.get("encode", 0.0)}


def lambda_bodies(width: int, height: int, requests: int) -> list[dict]:
    """A global value g (2, 3, … 8, 2, …) and a rectangle over the left half painted at 11 − g
    alternating: every map differs from the one before it (each value from its neighbours')."""
    values = [2.0 + (i // 2) % 7 for i in range(requests)]
    return [{"value": g} if i % 2 == 0 else
            {"rects": [{"x": 0, "y": 0, "w": max(1, width // 2), "h": height, "value": 11.0 - g}]}
            for i, g in enumerate(values)]


def timed_edit(client: httpx.Client, job_id: str, body: dict, previous_png: bytes | None) -> tuple[EditTiming, dict, bytes]:
    """One PUT, then the GET that reads its preview: (timing, the PUT's JSON, the PNG)."""
    started = time.perf_counter()
    put = client.put(f"/jobs/{job_id}/lambda", json=body)
    put_s = time.perf_counter() - started
    put.raise_for_status()
    version = put.json()["version"]
    started = time.perf_counter()
    get = client.get(f"/jobs/{job_id}/preview", params={"layer": "denoised", "format": "png", "v": version})
    get_s = time.perf_counter() - started
    get.raise_for_status()
    if int(get.headers["X-Preview-Version"]) < version:
        raise RuntimeError(f"the preview after λ edit version {version} is version {get.headers['X-Preview-Version']}")
    parts = edit_parts(put_s, get_s, parse_server_timing(put.headers.get(SERVER_TIMING)),
                       parse_server_timing(get.headers.get(SERVER_TIMING)))
    return EditTiming(put_s, get_s, parts, previous_png is not None and get.content != previous_png), put.json(), get.content


def settled_edit(client: httpx.Client, job_id: str, body: dict, previous_png: bytes | None) -> tuple[EditTiming, float, bytes]:
    """timed_edit, then GET result.exr, which answers once the edit's files (preview layers,
    result EXRs) are written: its Server-Timing "flush" is how long that still took. Returns
    (timing, seconds from the PUT's answer until the files landed, the PNG). The EXR is read to
    its end, so its transfer is over before the next edit starts."""
    edit, _, png = timed_edit(client, job_id, body, previous_png)
    result = client.get(f"/jobs/{job_id}/result.exr")
    result.raise_for_status()
    flush = parse_server_timing(result.headers.get(SERVER_TIMING)).get("flush", 0.0)
    return edit, edit.get_s + flush, png


def percentile_ms(seconds: list[float], q: float) -> float:
    return float(np.percentile(np.array(seconds) * 1e3, q))


def bench_http_lambda(size: int, requests: int, weights_dir: Path, seed: int, torch_threads: int,
                      height: int | None = None, spp: int = 16, encode_repeats: int = 0, settled: int = 0) -> dict:
    """p50/p95 of PUT /jobs/{id}/lambda round trips on a finished job (the cached λ tail path),
    alternating a global value and a painted rectangle so every request changes the image, each
    followed by the GET of its preview (EditTiming), after one untimed warm-up edit. The job is
    size² (size wide and `height` high when given), one iteration of `spp`. Then `settled` edits
    each once the one before has written its files (settled_edit): the round trip without them,
    and how long the files took after the answer. With `encode_repeats`, "encoding" is the last
    preview's PNG cost at two zlib levels (bench.preview_encoding)."""
    height = height or size
    with tempfile.TemporaryDirectory(prefix="renderloop-bench-") as tmp:
        with running_server(Path(tmp) / "data", weights_dir, torch_threads) as url, httpx.Client(base_url=url, timeout=600) as client:
            created = client.post("/jobs", json={"scene": "cornell-box", "width": size, "height": height,
                                                 "max_iterations": 1, "spp_first": spp, "seed": seed})
            created.raise_for_status()
            job_id = created.json()["id"]
            job = wait_for_job(client, job_id, timeout=3600)
            if job["state"] != "completed":
                raise RuntimeError(f"benchmark job ended {job['state']}: {job.get('error')}")
            edits, tail, full, png = [], 0, 0, None
            for i, body in enumerate(lambda_bodies(size, height, requests + 1)):
                edit, answer, png = timed_edit(client, job_id, body, png)
                if i == 0:
                    continue  # warm-up: the first λ may rebuild the cache (a Ray λ actor opens the job)
                edits.append(edit)
                tail += answer.get("tail_passes", 0)
                full += answer.get("full_passes", 0)
            calm, landed = [], []
            for body in lambda_bodies(size, height, settled):
                edit, seconds, png = settled_edit(client, job_id, body, png)
                calm.append(edit)
                landed.append(seconds)
            encoding = None
            if encode_repeats:  # untimed by the edits: after the last one
                exr = client.get(f"/jobs/{job_id}/preview", params={"layer": "denoised", "format": "exr"})
                exr.raise_for_status()
                encoding = time_preview_encoding(exr_from_bytes(exr.content).color, encode_repeats)
    put = [e.put_s for e in edits]
    return {"size": size, "height": height, "requests": len(edits), "p50_ms": percentile_ms(put, 50),
            "p95_ms": percentile_ms(put, 95), "max_ms": 1e3 * max(put), "tail_passes": tail, "full_passes": full,
            "readable_p50_ms": percentile_ms([e.readable_s for e in edits], 50),
            "readable_p95_ms": percentile_ms([e.readable_s for e in edits], 95),
            "get_p50_ms": percentile_ms([e.get_s for e in edits], 50),
            "parts_ms": {key: percentile_ms([e.parts[key] for e in edits], 50) for key, _ in EDIT_PARTS},
            "changed": sum(e.changed for e in edits), "unchanged": [i for i, e in enumerate(edits) if not e.changed],
            "spp": spp, "encoding": encoding, "settled": len(calm),
            "settled_readable_p50_ms": percentile_ms([e.readable_s for e in calm], 50) if calm else math.nan,
            "settled_tail_p50_ms": percentile_ms([e.parts["tail"] for e in calm], 50) if calm else math.nan,
            "files_landed_p50_ms": percentile_ms(landed, 50) if landed else math.nan}
