"""`renderloop serve …` itself as a subprocess, for tests of what only the command line sets up:
uvicorn's connection handling, the access log, --token-file. (service_harness.Server runs the
uvicorn factory instead, without these.) Thread backend, so no Ray start-up."""
from __future__ import annotations

import os
from pathlib import Path

from serve_process import start_serve
from service_harness import Server

STARTUP_SECONDS = 120.0
SECRET_ENV = ("RENDERLOOP_TOKEN", "RENDERLOOP_TOKEN_FILE", "RENDERLOOP_SERVER")


class CliServer(Server):
    def __init__(self, data_dir: Path, log_path: Path, args: list[str], env: dict[str, str] | None = None) -> None:
        super().__init__(data_dir, log_path, env)
        self.args = args

    def start(self) -> "CliServer":
        environment = {k: v for k, v in os.environ.items() if k not in SECRET_ENV}
        self.process = start_serve(["--port", str(self.port), "--data-dir", str(self.data_dir), "--concurrency", "1",
                                    *self.args], self.url, self.log_path, {**environment, **self.env}, STARTUP_SECONDS)
        return self
