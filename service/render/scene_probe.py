"""Scene checks at submit run in a child process with a memory and a wall-clock limit.

Flattening, parsing and instantiating an uploaded scene costs what the scene asks for: a 88 KB
zip of 4·10⁵ shapes took 48 s and 2.9 GB when the API process did it, and that memory stayed
with the server. Here every check gets its own short-lived process:

- a standby child is started ahead of time (Python, Mitsuba with its variant, the check's own
  module imported), so a small scene's check costs its own work, not the ~2 s start-up;
- it takes one request, walls its main thread in with Landlock (the bundle folder and the
  installed software only; scene loads inside it still use the per-load wall of
  service/render/sandbox.py), runs the check and answers with JSON (never pickle: the child
  reads hostile input, the parent must not execute what it sends back);
- the parent polls the child's resident memory and kills it past the limit, and kills it at the
  deadline; either way the caller gets `ProbeLimitExceeded` naming the limit and its setting;
- the child exits after one check, so nothing a scene allocated outlives it.

Dr.Jit and Mitsuba start thread pools and LLVM when the variant is set, so a child is started
with exec (subprocess), never forked from a process where they run. The child's environment
keeps only what Python, Dr.Jit and Mitsuba need: no service secrets (tokens, database URLs).
"""
from __future__ import annotations

import importlib
import json
import os
import select
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

DEFAULT_MEMORY_MB = 2048
DEFAULT_SECONDS = 30.0
DEFAULT_CONCURRENT = 2  # checks at once; each may use the memory limit
MEMORY_ENV = "RENDERLOOP_SCENE_CHECK_MEMORY_MB"
SECONDS_ENV = "RENDERLOOP_SCENE_CHECK_SECONDS"
MEMORY_FLAG = "--scene-check-memory-mb"
SECONDS_FLAG = "--scene-check-seconds"
STARTUP_SECONDS = 120.0  # a cold child on a loaded machine; not counted against the scene
POLL_SECONDS = 0.02  # the memory watchdog's period
ORPHAN_GRACE_SECONDS = 5  # a child whose parent died ends this long after its time limit
STDERR_FD = 2  # the server log: Mitsuba writes its warnings to stdout
# What the child's environment keeps (names, or prefixes ending in "_").
ENV_KEEP = ("PATH", "HOME", "LANG", "TZ", "TMPDIR", "LD_LIBRARY_PATH", "LC_", "PYTHON", "DRJIT_", "CUDA_",
            "NVIDIA_", "OMP_", "MKL_", "RENDERLOOP_VARIANT", "RENDERLOOP_TORCH_THREADS")

Check = Callable[[dict], dict]


@dataclass(frozen=True)
class ProbeLimits:
    memory_bytes: int = DEFAULT_MEMORY_MB * 2**20  # resident memory the check may add to an idle child
    seconds: float = DEFAULT_SECONDS
    concurrent: int = DEFAULT_CONCURRENT

    @classmethod
    def from_env(cls) -> "ProbeLimits":
        megabytes, seconds = os.environ.get(MEMORY_ENV), os.environ.get(SECONDS_ENV)
        return cls(memory_bytes=int(float(megabytes) * 2**20) if megabytes else cls.memory_bytes,
                   seconds=float(seconds) if seconds else cls.seconds)


class ProbeLimitExceeded(Exception):
    """The check went over a limit (or its process died); the message says which and how to
    raise it."""

    def __init__(self, limit: str, message: str) -> None:
        super().__init__(message)
        self.limit = limit  # "memory", "time" or "crash"


class ProbeFailed(RuntimeError):
    """The check raised something it does not turn into an answer: a bug, not bad input."""


def child_environment() -> dict[str, str]:
    return {name: value for name, value in os.environ.items()
            if any(name == keep or (keep.endswith("_") and name.startswith(keep)) for keep in ENV_KEEP)}


def resident_bytes(pid: int) -> int:
    """VmRSS of a process (0 once it is gone)."""
    try:
        with open(f"/proc/{pid}/status") as status:
            for line in status:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) * 1024
    except (FileNotFoundError, ProcessLookupError):
        pass
    return 0


class _Child:
    """One checking process: started warm, used once."""

    def __init__(self, preload: str) -> None:
        read_end, write_end = os.pipe()
        self.process = subprocess.Popen(
            [sys.executable, "-m", __name__, str(write_end), preload], stdin=subprocess.PIPE,
            stdout=STDERR_FD, pass_fds=(write_end,), env=child_environment(), close_fds=True)
        os.close(write_end)
        self.replies = read_end
        self.buffer = b""
        self.baseline = 0

    def wait_ready(self) -> None:
        message = self._read_line(time.monotonic() + STARTUP_SECONDS, watch=None)
        if message is None or not message.get("ready"):
            raise ProbeFailed(f"the scene-check process did not start: {message}")
        self.baseline = resident_bytes(self.process.pid)

    def ask(self, request: dict, limits: ProbeLimits) -> dict:
        self.process.stdin.write(json.dumps(request).encode() + b"\n")
        self.process.stdin.flush()
        reply = self._read_line(time.monotonic() + limits.seconds, watch=limits)
        if reply is None:
            raise ProbeLimitExceeded("crash", f"the scene check ended abnormally ({self._ending()}); "
                                              "the scene cannot be loaded")
        return reply

    def _read_line(self, deadline: float, watch: ProbeLimits | None) -> dict | None:
        """The next JSON line from the child, or None at EOF; enforces the limits meanwhile."""
        while b"\n" not in self.buffer:
            ready, _, _ = select.select([self.replies], [], [], POLL_SECONDS)
            if ready:
                chunk = os.read(self.replies, 1 << 16)
                if not chunk:
                    return None
                self.buffer += chunk
                continue
            if watch is not None and resident_bytes(self.process.pid) - self.baseline > watch.memory_bytes:
                self.close()
                raise ProbeLimitExceeded("memory", f"loading the scene needs more than {watch.memory_bytes // 2**20} MiB "
                                                   f"(raise it with serve {MEMORY_FLAG} N or {MEMORY_ENV})")
            if time.monotonic() > deadline:
                self.close()
                if watch is None:
                    raise ProbeFailed("the scene-check process did not start in time")
                raise ProbeLimitExceeded("time", f"checking the scene took longer than {watch.seconds:g} s "
                                                 f"(raise it with serve {SECONDS_FLAG} S or {SECONDS_ENV})")
        line, _, self.buffer = self.buffer.partition(b"\n")
        return json.loads(line)

    def _ending(self) -> str:
        code = self.process.wait()
        return f"signal {signal.Signals(-code).name}" if code < 0 else f"exit status {code}"

    def close(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
        self.process.wait()
        if self.process.stdin is not None:
            self.process.stdin.close()
        if self.replies >= 0:
            os.close(self.replies)
            self.replies = -1


class SceneProber:
    """Runs `check(payload) -> dict` (a module-level function) in a fresh child per call.
    `preload`: the module the checks live in, imported by standby children ahead of time."""

    def __init__(self, limits: ProbeLimits = ProbeLimits(), preload: str = "service.render.scenes") -> None:
        self.limits = limits
        self.preload = preload
        self._slots = threading.BoundedSemaphore(limits.concurrent)
        self._lock = threading.Lock()
        self._standby: _Child | None = None
        self._closed = False

    def start(self) -> None:
        """Start a standby child now, so the first check is warm too."""
        with self._lock:
            if self._standby is None and not self._closed:
                self._standby = _Child(self.preload)

    def run(self, check: Check, payload: dict, readable: list[Path]) -> dict:
        """`check(payload)` in a child that may read only `readable` (and the software)."""
        request = {"check": f"{check.__module__}:{check.__qualname__}", "payload": payload,
                   "readable": [str(Path(p).resolve()) for p in readable], "seconds": self.limits.seconds}
        with self._slots:
            child = self._take()
            try:
                child.wait_ready()
                reply = child.ask(request, self.limits)
            finally:
                child.close()
        if "crash" in reply:
            raise ProbeFailed(reply["crash"])
        return reply["result"]

    def _take(self) -> _Child:
        """The standby child (a new one if none is waiting); a replacement starts warming."""
        with self._lock:
            if self._closed:
                raise ProbeFailed("the scene checker is shut down")
            child, self._standby = self._standby, _Child(self.preload)
        if child is None or child.process.poll() is not None:  # none waiting, or it died while idle
            if child is not None:
                child.close()
            child = _Child(self.preload)
        return child

    def close(self) -> None:
        with self._lock:
            self._closed = True
            standby, self._standby = self._standby, None
        if standby is not None:
            standby.close()


# -- the child ----------------------------------------------------------------------------------

def _resolve(name: str) -> Check:
    module, _, qualname = name.partition(":")
    target = importlib.import_module(module)
    for part in qualname.split("."):
        target = getattr(target, part)
    return target


def _child_main(reply_fd: int, preload: str) -> None:
    from service.render.runtime import mitsuba
    from service.render.sandbox import restrict_current_thread, software_roots, wall_support

    replies = os.fdopen(reply_fd, "w")

    def answer(message: dict) -> None:
        replies.write(json.dumps(message) + "\n")
        replies.flush()

    mitsuba()
    importlib.import_module(preload)
    software_roots()  # found before the wall: it looks at folders the wall then hides
    answer({"ready": True})
    line = sys.stdin.readline()
    if not line:
        return  # the parent closed without a request (shutdown)
    request = json.loads(line)
    # The parent enforces the limits; should it die mid-check, the alarm still ends this process.
    signal.alarm(int(request["seconds"]) + ORPHAN_GRACE_SECONDS)
    try:
        check = _resolve(request["check"])
        if wall_support().available:
            restrict_current_thread([Path(p) for p in request["readable"]])
        answer({"result": check(request["payload"])})
    except Exception as exc:  # noqa: BLE001 - reported to the parent as a bug in the check
        answer({"crash": f"{type(exc).__name__}: {exc}"})


if __name__ == "__main__":
    _child_main(int(sys.argv[1]), sys.argv[2])
