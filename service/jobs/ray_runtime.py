"""The Ray runtime a server uses, sealed: a local one bound to loopback behind Ray's token auth,
with the service's own secrets kept out of its processes; a cluster joined only with token auth
(unless the operator says `--insecure-ray`).

What Ray 2.60 offers, measured (docs/security.md, "Ray"):
- `ray.init(_node_ip_address="127.0.0.1")` is rewritten to the host's address
  (`services.resolve_ip_for_localhost`) and GCS, raylet, workers and agents keep listening on
  every interface. Ray's single-machine mode (RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0, what it
  runs on macOS) makes the node's address 127.0.0.1, and then every Ray process — GCS, raylet,
  object manager, workers, dashboard, dashboard agent, runtime-env agent, metrics exporters —
  binds loopback. The dashboard agent and the monitor cannot be left out of `ray.init`;
  bound to loopback and behind the token they are sealed.
- Token auth: RAY_AUTH_MODE=token, the token read from RAY_AUTH_TOKEN_PATH. Left alone, Ray
  writes ~/.ray/auth_token world-readable (0644); ours lives in a private folder (0700),
  the file 0600, and is removed when the runtime stops.
- Ray's processes inherit the driver's environment at `ray.init` (workers inherit the
  raylet's), so the secrets are taken out of it for that call only.
- `ray.init` replaces the SIGTERM handler of the calling thread's process with one that calls
  `sys.exit` (a traceback and a C++ abort in a server); the previous handler is put back.
"""
from __future__ import annotations

import functools
import logging
import os
import secrets
import shutil
import signal
import tempfile
import threading
from contextlib import contextmanager
from pathlib import Path
from types import FrameType
from typing import Callable, Iterator

import ray

from service.jobs.ray_auth import (AUTH_MODE_ENV, AUTH_TOKEN_ENV, AUTH_TOKEN_PATH_ENV, RayAuthMissing,
                                    cluster_auth_problem)

log = logging.getLogger(__name__)

SINGLE_MACHINE_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"  # "0": Ray's node address is loopback
# The service's own secrets: none is needed by a Ray worker (actors never touch the job store).
SECRET_ENV = ("RENDERLOOP_TOKEN", "RENDERLOOP_TOKEN_FILE", "RENDERLOOP_DB", "PGPASSWORD", "PGPASSFILE")
# Ray's timeouts, for this server's life (an operator's value wins). Start-up: on a loaded
# 2-core machine the GCS can take well over Ray's 60 s default to answer ("Failed to connect to
# GCS within 60 seconds"). Shutdown: the driver flushes task events to the GCS for up to 5 s
# before it lets go, which a SIGTERM to the whole process group (the GCS already gone) turns
# into a plain wait: 7 s of ray.shutdown, measured, 2.4 s with the flush cut to 0.3 s.
RAY_TIMEOUTS = {
    "RAY_gcs_rpc_server_connect_timeout_s": "300",
    "RAY_py_gcs_connect_timeout_s": "300",
    "RAY_gcs_server_request_timeout_seconds": "300",
    "RAY_task_events_shutdown_flush_timeout_ms": "300",
}
# Ray starts its worker processes at nice 15 to keep its own daemons responsive; here the workers
# are the service's whole work (the thread backend renders at the server's priority), and on a
# shared host nice 15 starves them: measured beside two nice-5/10 jobs on 2 cores, two workers
# took twice the compute time of one. A cluster joined with --ray-address keeps its own setting
# (RAY_worker_niceness, see docker/compose.yaml).
WORKER_NICENESS = 0
START_ATTEMPTS = 2
# Ray features the service does not use, off for the processes of the local runtime: metrics
# collection (one listening exporter less, measured: 11 → 10 ports).
UNUSED_FEATURES = {"RAY_enable_metrics_collection": "0"}
# Without these no job runs: the GCS, the raylet, and the dashboard agent (Ray 2.60's raylet
# ends when its agent dies, measured with kill -9).
VITAL_DAEMONS = ("ray", "gcs_server", "raylet", "dashboard_agent", "runtime_env_agent")


def secret_names(environ: dict[str, str] | os._Environ) -> list[str]:
    """The variables of `environ` that carry the service's secrets."""
    return [name for name in environ if name in SECRET_ENV]


@contextmanager
def environment(set_: dict[str, str], remove: list[str]) -> Iterator[None]:
    """os.environ with `set_` applied and `remove` taken out, restored afterwards: what the
    processes started inside inherit."""
    saved = {name: os.environ.get(name) for name in [*set_, *remove]}
    os.environ.update(set_)
    for name in remove:
        os.environ.pop(name, None)
    try:
        yield
    finally:
        for name, value in saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


@contextmanager
def signal_handlers_kept() -> Iterator[None]:
    """Ray's `ray.init` installs its own SIGTERM handler (sys.exit); the server's stays."""
    if threading.current_thread() is not threading.main_thread():
        yield  # signal handlers can only be read and set from the main thread; Ray skips it too
        return
    saved = {number: signal.getsignal(number) for number in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield
    finally:
        for number, handler in saved.items():
            if handler is not None:
                signal.signal(number, handler)


def chain_sigterm(first: Callable[[], None]) -> Callable[[], None]:
    """Run `first` on SIGTERM, then whatever handler was there (uvicorn's graceful shutdown):
    the backend learns of the stop at once, not after uvicorn's grace for open responses — a
    SIGTERM to the whole process group ends Ray's workers in the same instant, and a job must
    not take that for a crash and start new ones."""
    if threading.current_thread() is not threading.main_thread():
        return lambda: None
    previous = signal.getsignal(signal.SIGTERM)

    def handler(signum: int, frame: FrameType | None) -> None:
        first()
        if callable(previous):
            previous(signum, frame)
        elif previous == signal.SIG_DFL:
            raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, handler)

    def unchain() -> None:
        """Put the previous handler back, if ours is still the one installed."""
        if threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGTERM) is handler:
            signal.signal(signal.SIGTERM, previous)

    return unchain


@functools.cache
def process_token() -> str:
    """This process's Ray token, random, made once: Ray's driver loads the token the first time
    it needs one and keeps it for the life of the process, so a local runtime started again in
    the same process (after `stop`) must carry the same value, or its GCS refuses the driver
    (InvalidAuthToken, "Failed to start GCS")."""
    return secrets.token_hex(32)


def private_token_file() -> Path:
    """This process's token in a fresh folder only this user can read (the folder 0700, the file 0600)."""
    folder = Path(tempfile.mkdtemp(prefix="renderloop-ray-"))  # mkdtemp: mode 0700
    path = folder / "auth_token"
    descriptor = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    with os.fdopen(descriptor, "w") as token:
        token.write(process_token())
    return path


class LocalRay:
    """The local runtime this server starts: `start` brings it up sealed, `stop` ends it and
    removes its token. `alive` says whether Ray's own daemons still run."""

    def __init__(self, cpus: int) -> None:
        self.cpus = cpus
        self.token_path: Path | None = None

    def start(self) -> None:
        self.token_path = private_token_file()
        # Kept for the life of the runtime: the driver's token loader and any process Ray starts
        # later read the token from this path.
        os.environ[AUTH_TOKEN_PATH_ENV] = str(self.token_path)
        os.environ.pop(AUTH_TOKEN_ENV, None)  # a token in the environment would win over the file
        # Unset, Ray turns token auth on for a new local cluster and refreshes its cached config
        # (set beforehand, the driver keeps the mode it read at import); an operator's
        # RAY_AUTH_MODE=disabled is not honoured here.
        os.environ.pop(AUTH_MODE_ENV, None)
        for name, value in RAY_TIMEOUTS.items():
            os.environ.setdefault(name, value)
        inherited = {SINGLE_MACHINE_ENV: "0", **UNUSED_FEATURES}
        with environment(inherited, secret_names(os.environ)), signal_handlers_kept():
            _loopback_node_address()
            self._init_with_retries()
        if os.environ.get(AUTH_MODE_ENV) != "token":
            self.stop()
            raise RuntimeError("Ray did not enable token auth for the local runtime; refusing to run without it")

    def _init_with_retries(self) -> None:
        """ray.init, tried again after a failed start: on a loaded machine a start can time out
        in places Ray does not let us tune (the raylet's registration waits 30 s)."""
        for attempt in range(1, START_ATTEMPTS + 1):
            try:
                ray.init(num_cpus=self.cpus, include_dashboard=False, log_to_driver=False,
                         _system_config={"worker_niceness": WORKER_NICENESS})
                return
            except Exception as exc:  # Ray raises plain Exception/RuntimeError on a timed-out start
                ray.shutdown()
                if attempt == START_ATTEMPTS:
                    raise
                log.warning("starting the local Ray runtime failed (%s); trying again", exc)

    def stop(self) -> None:
        with signal_handlers_kept():
            ray.shutdown()
        self.remove_token()

    def remove_token(self) -> None:
        """Delete the token and its folder (also on the way out after Ray died)."""
        if self.token_path is not None:
            shutil.rmtree(self.token_path.parent, ignore_errors=True)
            if os.environ.get(AUTH_TOKEN_PATH_ENV) == str(self.token_path):
                os.environ.pop(AUTH_TOKEN_PATH_ENV)
            self.token_path = None

    def failure(self) -> str | None:
        """Which of Ray's daemons this runtime cannot work without has died, if one has."""
        dead = [name for name in self.dead_daemons() if name in VITAL_DAEMONS]
        return f"the local Ray runtime lost its {', '.join(dead)}" if dead else None

    @staticmethod
    def dead_daemons() -> list[str]:
        """Ray's own processes of this runtime (GCS, raylet, agents…) that have exited."""
        node = ray._private.worker._global_node  # Ray keeps its local processes only here
        if node is None:
            return ["ray"]
        dead = []
        for kind, infos in dict(node.all_processes).items():
            dead += [kind for info in infos if info.process is not None and info.process.poll() is not None]
        return dead


def _loopback_node_address() -> None:
    """Ray reads SINGLE_MACHINE_ENV once, at import; the server imported Ray before this call,
    so the module's copy follows the environment here (the processes Ray starts read it anew)."""
    from ray._private import ray_constants

    ray_constants.ENABLE_RAY_CLUSTER = os.environ.get(SINGLE_MACHINE_ENV) != "0"


def join_cluster(address: str, insecure: bool) -> None:
    """Connect to the cluster at `address`, refusing to without token auth unless `insecure`."""
    problem = cluster_auth_problem()
    if problem is not None and not insecure:
        raise RayAuthMissing(problem)
    if problem is not None:
        log.warning("--insecure-ray: %s", problem)
    with environment({}, secret_names(os.environ)), signal_handlers_kept():
        ray.init(address=address, log_to_driver=False)
