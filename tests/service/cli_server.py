"""`renderloop serve …` itself as a subprocess, for tests of what only the command line sets up:
uvicorn's connection handling, the access log, --token-file. (service_harness.Server runs the
uvicorn factory instead, without these.) Thread backend, so no Ray start-up."""
from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import httpx

from service_harness import REPO, Server

STARTUP_SECONDS = 120.0
SECRET_ENV = ("RENDERLOOP_TOKEN", "RENDERLOOP_TOKEN_FILE", "RENDERLOOP_SERVER")


class CliServer(Server):
    def __init__(self, data_dir: Path, log_path: Path, args: list[str], env: dict[str, str] | None = None) -> None:
        super().__init__(data_dir, log_path, env)
        self.args = args

    def start(self) -> "CliServer":
        environment = {k: v for k, v in os.environ.items() if k not in SECRET_ENV}
        env = {**environment, "PYTHONUNBUFFERED": "1", **self.env}
        command = [sys.executable, "-m", "service.cli", "serve", "--port", str(self.port),
                   "--data-dir", str(self.data_dir), "--concurrency", "1", *self.args]
        log = open(self.log_path, "ab")
        self.process = subprocess.Popen(command, cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + STARTUP_SECONDS
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"server exited early:\n{self.log()}")
            try:
                if httpx.get(self.url + "/healthz", timeout=2).status_code == 200:
                    return self
            except httpx.TransportError:
                time.sleep(0.3)
        raise RuntimeError(f"server did not come up:\n{self.log()}")
