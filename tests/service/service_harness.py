"""Test harness for the job service. A real server (uvicorn running
`service.api.serve:app_from_env`, see service_launcher.py) in a subprocess on a free port, a real httpx client, the SQLite file in tmp_path. A subprocess (not a thread)
so tests can `kill -9` it and start another on the same data dir."""
from __future__ import annotations

import io
import os
import signal
import socket
import stat
import subprocess
import sys
import time
import zipfile
from pathlib import Path
from typing import Callable

import httpx

REPO = Path(__file__).resolve().parents[2]
LAUNCHER = Path(__file__).with_name("service_launcher.py")
STARTUP_SECONDS = 60.0


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


class Server:
    def __init__(self, data_dir: Path, log_path: Path, env: dict[str, str] | None = None,
                 cwd: Path = REPO, startup_seconds: float = STARTUP_SECONDS) -> None:
        self.env = env or {}
        self.startup_seconds = startup_seconds  # a Ray runtime on a loaded machine takes longer
        self.cwd = cwd  # the server's working directory: a relative data_dir is relative to it
        self.data_dir = data_dir
        self.log_path = log_path
        self.port = free_port()
        self.process: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def start(self) -> "Server":
        env = {**os.environ, "RENDERLOOP_DATA_DIR": str(self.data_dir), "PYTHONUNBUFFERED": "1", **self.env}
        command = [sys.executable, str(LAUNCHER), str(self.port)]
        log = open(self.log_path, "ab")
        self.process = subprocess.Popen(command, cwd=self.cwd, env=env, stdout=log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + self.startup_seconds
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"server exited early:\n{self.log()}")
            try:
                if httpx.get(self.url + "/healthz", timeout=1).status_code == 200:
                    return self
            except httpx.TransportError:
                time.sleep(0.2)
        raise RuntimeError(f"server did not come up:\n{self.log()}")

    def log(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""

    def kill(self) -> None:
        """`kill -9`: no shutdown hooks, whatever was in flight is lost."""
        if self.process and self.process.poll() is None:
            os.kill(self.process.pid, signal.SIGKILL)
            self.process.wait(10)

    def stop(self) -> None:
        if self.process and self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(20)
            except subprocess.TimeoutExpired:
                self.kill()


def wait_for(client: httpx.Client, job_id: str, done: Callable[[dict], bool], timeout: float = 180) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job = client.get(f"/jobs/{job_id}").json()
        if done(job):
            return job
        if job["state"] in ("failed", "canceled") and not done(job):
            raise AssertionError(f"job ended as {job['state']}: {job}")
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting; last status {job}")


def finished(job: dict) -> bool:
    return job["state"] in ("completed", "failed", "canceled")


def cli_environment(env: dict[str, str] | None = None) -> dict[str, str]:
    """This process's environment without RENDERLOOP_SERVER/TOKEN, plus `env`."""
    environment = {k: v for k, v in os.environ.items() if k not in ("RENDERLOOP_SERVER", "RENDERLOOP_TOKEN")}
    return {**environment, **(env or {})}


def renderloop_cli(*args: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """`renderloop ARGS…` as a real subprocess, without the caller's RENDERLOOP_SERVER/TOKEN."""
    return subprocess.run([sys.executable, "-m", "service.cli", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=300, env=cli_environment(env))


def renderloop_clis(*argvs: list[str]) -> list[subprocess.CompletedProcess]:
    """Several independent `renderloop` commands as real subprocesses at once (each start is
    mostly imports: two cores run two at a time), in the order given."""
    processes = [subprocess.Popen([sys.executable, "-m", "service.cli", *argv], cwd=REPO, stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True, env=cli_environment()) for argv in argvs]
    results = []
    for process in processes:
        stdout, stderr = process.communicate(timeout=300)
        results.append(subprocess.CompletedProcess(process.args, process.returncode, stdout, stderr))
    return results


def zip_bytes(members: dict[str, bytes | str], symlinks: dict[str, str] = {}) -> bytes:
    """A zip with the given members, plus symlink entries (name → target) as a hostile bundle has."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as zf:
        for name, data in members.items():
            zf.writestr(name, data)
        for name, target in symlinks.items():
            info = zipfile.ZipInfo(name)
            info.external_attr = (stat.S_IFLNK | 0o777) << 16
            zf.writestr(info, target)
    return buffer.getvalue()
