"""`renderloop serve` itself as a subprocess for the tests (the console script's code path, not
the test launcher), in its own session so a test can signal its whole process group."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx

import iteration_hold
from service_harness import REPO, free_port

RAY_STARTUP_SECONDS = 300  # a Ray runtime on a loaded 2-core machine can take minutes
HOLD_SITE = Path(__file__).with_name("hold_site")  # its sitecustomize installs iteration_hold in every process
BACKENDS = {"threads": ["--concurrency", "1"], "ray": ["--workers", "1"]}


def start_serve(args: list[str], url: str, log_path: Path, env: dict[str, str], startup_seconds: float,
                new_session: bool = False) -> subprocess.Popen:
    """`renderloop serve ARGS` as a subprocess logging to `log_path`, once its /healthz answers 200."""
    with open(log_path, "ab") as log:
        process = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", *args], cwd=REPO,
                                   env={**env, "PYTHONUNBUFFERED": "1"}, stdout=log, stderr=subprocess.STDOUT,
                                   start_new_session=new_session)
    deadline = time.monotonic() + startup_seconds
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"server exited early:\n{log_path.read_text(errors='replace')}")
        try:
            if httpx.get(url + "/healthz", timeout=2).status_code == 200:
                return process
        except httpx.TransportError:
            pass
        time.sleep(0.2)
    raise RuntimeError(f"server did not come up:\n{log_path.read_text(errors='replace')}")


class ServeProcess:
    """`renderloop serve` itself (the console script's code path, not the test launcher)."""

    def __init__(self, data_dir: Path, log_path: Path, backend: list[str], hold: str | None = None) -> None:
        """`hold` (iteration_hold.hold_value): the server's jobs hold inside a render, in the
        server's process and in its Ray workers alike (hold_site/sitecustomize.py)."""
        self.data_dir, self.log_path, self.backend, self.hold = data_dir, log_path, backend, hold
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.process: subprocess.Popen | None = None

    def start(self) -> "ServeProcess":
        env = {k: v for k, v in os.environ.items()
               if k not in ("RENDERLOOP_TOKEN", "RENDERLOOP_CONCURRENCY", iteration_hold.ENV)}
        if self.hold is not None:
            env[iteration_hold.ENV] = self.hold
            env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(HOLD_SITE), env.get("PYTHONPATH")]))
        # Its own session: a process-group signal reaches this server's group and nothing of pytest.
        self.process = start_serve(["--port", str(self.port), "--data-dir", str(self.data_dir), *self.backend],
                                   self.url, self.log_path, env, RAY_STARTUP_SECONDS, new_session=True)
        return self

    def log(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""

    def close(self) -> None:
        if self.process is not None and self.process.poll() is None:
            os.killpg(self.process.pid, signal.SIGKILL)
            self.process.wait(30)
