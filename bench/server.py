"""A real uvicorn server in a subprocess, and the λ-over-HTTP latency measured against it.

The server is exactly `service.api.serve.app_from_env`, so the figure includes routing, JSON,
the job store and the cached λ tail: what a user sees.
"""
from __future__ import annotations

import os
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import numpy as np
import uvicorn

from models.pretrained import WEIGHTS_DIR_ENV
from service.api.serve import DATA_DIR_ENV, app_from_env
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


def bench_http_lambda(size: int, requests: int, weights_dir: Path, seed: int, torch_threads: int,
                      height: int | None = None) -> dict:
    """p50/p95 of PUT /jobs/{id}/lambda round trips on a finished job (the cached λ tail path),
    alternating a global value and a painted rectangle so every request changes the image.
    The job is size² (size wide and `height` high when given), one 16-spp iteration."""
    with tempfile.TemporaryDirectory(prefix="renderloop-bench-") as tmp:
        with running_server(Path(tmp) / "data", weights_dir, torch_threads) as url, httpx.Client(base_url=url, timeout=120) as client:
            created = client.post("/jobs", json={"scene": "cornell-box", "width": size, "height": height or size,
                                                 "max_iterations": 1, "seed": seed})
            created.raise_for_status()
            job_id = created.json()["id"]
            job = wait_for_job(client, job_id)
            if job["state"] != "completed":
                raise RuntimeError(f"benchmark job ended {job['state']}: {job.get('error')}")
            bodies = [{"value": 2.0 + (i % 7)} if i % 2 == 0 else
                      {"rects": [{"x": 0, "y": 0, "w": max(1, size // 2), "h": height or size, "value": 10.0 - (i % 5)}]}
                      for i in range(requests + 1)]
            seconds, tail, full = [], 0, 0
            for i, body in enumerate(bodies):
                t0 = time.perf_counter()
                response = client.put(f"/jobs/{job_id}/lambda", json=body)
                elapsed = time.perf_counter() - t0
                response.raise_for_status()
                if i == 0:
                    continue  # warm-up: the first λ may rebuild the cache
                seconds.append(elapsed)
                tail += response.json().get("tail_passes", 0)
                full += response.json().get("full_passes", 0)
    ms = np.array(seconds) * 1e3
    return {"size": size, "height": height or size, "requests": len(seconds), "p50_ms": float(np.percentile(ms, 50)),
            "p95_ms": float(np.percentile(ms, 95)), "max_ms": float(ms.max()), "tail_passes": tail, "full_passes": full}

