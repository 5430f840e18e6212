"""`renderloop render|denoise|serve|submit|jobs|status|cancel|download|delete|bench|dataset|train` (docs/cli.md).

Every user error ends as one `renderloop: error: …` line and exit status 2; tracebacks are
for bugs only.
"""
from __future__ import annotations

import argparse
from dataclasses import replace
import os
import sys
import time
from pathlib import Path

from service import client_command, denoise_command, train_command
from service.bench_command import BenchNotInstalled, load_bench_main
from service.api.security import (LOOPBACK_HOSTS, TOKEN_ENV, TOKEN_FILE_ENV, SecuritySettings, TokenFileError,
                                  is_loopback, read_token_file)
from service.api.edge_settings import HEADER_TIMEOUT_SECONDS, KEEP_ALIVE_SECONDS, MAX_CONNECTIONS, EdgeSettings
from service.api.streams import MAX_STREAMS_PER_CLIENT
from service.jobs.ray_auth import cluster_auth_problem
from service.jobs.worker_settings import WorkerSettings
from service.jobs.bundle import MAX_BUNDLE_BYTES, MAX_BUNDLE_FILES, BundleLimits
from service.jobs.db.url import is_postgres_url, without_password
from service.jobs.errors import StoreUnavailable
from service.jobs.quotas import (DEFAULT_MAX_QUEUED, DEFAULT_MAX_QUEUED_PER_CLIENT, MAX_QUEUED_ENV,
                                 MAX_QUEUED_PER_CLIENT_ENV, Quotas)
from service.jobs.retention import Retention
from service.render.scene_probe import MEMORY_ENV, SECONDS_ENV, ProbeLimits
from service.job_options import JobOptionError, add_job_options, gives_stopping_rule, spec_from_args
from service.memory_reuse import keep_freed_memory
from service.loop.budget import describe_budget, scene_budget
from service.loop.spec import SERVICE_LIMITS, LoopSpec, LoopSpecError
from service.loop.stop_message import stop_message
from service.dataset import command as dataset_command

EXIT_USAGE = 2
DESCRIPTION = ("Adaptive-sampling renders of Mitsuba 3 scenes, denoised, as commands or as an HTTP service. "
               "Every command and flag: docs/cli.md; how it works: docs/design.md.")


class CliError(Exception):
    """A user-facing error: printed as one line, exit status 2."""


def load_cli_networks(weights: Path | None):
    """Torch threads and networks, chosen once per command and passed down (docs/design.md)."""
    from models.pretrained import load_networks
    from service.loop.tensors import configure_torch_threads
    from service.render.runtime import network_device

    configure_torch_threads()
    return load_networks(weights, device=network_device())


# -- render -----------------------------------------------------------------------------------

def add_render_parser(sub) -> None:
    p = sub.add_parser("render", help="render a scene with the adaptive loop (or one uniform pass)")
    p.add_argument("scene", nargs="?", help="Mitsuba 3 XML file or built-in scene name (see --list)")
    p.add_argument("--list", action="store_true", help="print the built-in scenes and exit")
    p.add_argument("--explain", action="store_true",
                   help="print the effects report (which integrator runs and why, what is simulated) and exit")
    add_job_options(p, service=False)  # the same options as `renderloop submit` (service/job_options.py)
    p.add_argument("-o", "--output", type=Path, help="output EXR path")
    p.add_argument("--weights", type=Path, help="folder holding denoiser.pt and error_predictor.pt "
                   "(default: $RENDERLOOP_WEIGHTS_DIR, else the shipped weights)")
    p.set_defaults(handler=run_render)


def render_spec(args) -> LoopSpec:
    return spec_from_args(args, args.scene)


def default_budget(args, spec: LoopSpec) -> LoopSpec:
    """With no stopping rule given, the scene's own sample_count is the budget (service/loop/budget.py)."""
    if gives_stopping_rule(args):
        return spec
    from service.render.scenes import scene_sample_count

    return scene_budget(spec, scene_sample_count(spec.scene, params=spec.params))


def run_render(args) -> int:
    from service.render.scenes import describe_builtin_scenes

    if args.list:
        for name, description in describe_builtin_scenes():
            print(f"{name:20s} {description}")
        return 0
    if not args.scene:
        raise CliError("render needs a SCENE (an XML file or a built-in name; see --list)")
    spec = default_budget(args, render_spec(args))
    if args.explain:
        from service.render.effects import explain_effects, inspect_scene

        effects = inspect_scene(spec.scene, frames=spec.frames, width=spec.width, height=spec.height,
                                params=spec.params)
        print(explain_effects(effects))
        print(describe_budget(spec))
        return 0
    if args.output is None:
        raise CliError("render needs -o OUT.exr")
    from service.exr import require_exr_path

    require_exr_path(args.output)  # before the render, not after it

    from tqdm import tqdm

    from service.exr import frame_path, write_exr
    from service.images import tonemap, write_png
    from service.loop.loop import RenderLoop

    loop = RenderLoop(spec, load_cli_networks(args.weights) if spec.denoise else None)
    bar = tqdm(total=spec.max_iterations, unit="it", desc=Path(spec.scene).stem, file=sys.stderr)
    record, started = None, time.perf_counter()
    for record in loop.run():
        err = "-" if record.predicted_error is None else f"{record.predicted_error:.4f}"
        bar.set_postfix(spp=f"{record.spp_mean:.1f}", error=err, refresh=False)
        bar.update(1)
    bar.close()
    for f, frame in enumerate(loop.result_frames()):
        path = write_exr(frame_path(args.output, f, spec.frames), frame)
        print(f"wrote {path}")
        if args.png:
            print(f"wrote {write_png(path.with_suffix('.png'), tonemap(frame.color))}")
    if record is not None:
        said = stop_message(spec, record.stop_reason, record.iteration + 1, record.spp_mean,
                            time.perf_counter() - started, record.predicted_error)
        print(f"{record.iteration + 1} iterations, {record.spp_mean:.1f} spp mean, stop: {record.stop_reason}"
              f"{f' ({said})' if said else ''}; {describe_budget(spec)}")
    return 0


# -- serve ------------------------------------------------------------------------------------

def add_serve_parser(sub) -> None:
    p = sub.add_parser("serve", help="run the HTTP service")
    p.add_argument("--host", default="127.0.0.1")
    p.add_argument("--port", type=int, default=8000)
    p.add_argument("--data-dir", type=Path, default=Path(os.environ.get("RENDERLOOP_DATA_DIR", "data")))
    p.add_argument("--db", metavar="URL", default=os.environ.get("RENDERLOOP_DB") or None,
                   help="job records in PostgreSQL, e.g. postgresql://user@host:5432/renderloop, shared by several "
                        "servers (default: $RENDERLOOP_DB, else DATA_DIR/jobs.sqlite); job files stay in the data dir")
    backend = p.add_mutually_exclusive_group()
    backend.add_argument("--workers", type=int, default=None,
                         help="Ray workers on a local Ray runtime this server starts: jobs (or shares of a sequence's "
                              "frames) rendered at once, one CPU each (default: one per core). The default backend; "
                              "with none of --workers/--ray-address/--concurrency: $RENDERLOOP_CONCURRENCY, "
                              "$RENDERLOOP_WORKERS, $RENDERLOOP_RAY_ADDRESS decide")
    backend.add_argument("--ray-address", metavar="ADDRESS", default=None,
                         help="join the Ray cluster at ADDRESS (e.g. 10.0.0.5:6379, from `ray start --head`) instead "
                              "of starting one; all nodes must share the data dir. Needs Ray's token auth "
                              "(RAY_AUTH_MODE=token, RAY_AUTH_TOKEN_PATH) unless --insecure-ray")
    backend.add_argument("--concurrency", type=int, default=None,
                         help="no Ray: render N jobs at once in threads of the server process (the in-process "
                              "backend; a job cannot be killed mid-iteration nor limited in memory)")
    p.add_argument("--insecure-ray", action="store_true",
                   help="join --ray-address even without Ray's token auth (anyone who reaches the cluster can run "
                        "code as this server)")
    p.add_argument("--weights", type=Path, help="folder holding denoiser.pt and error_predictor.pt "
                   "(default: $RENDERLOOP_WEIGHTS_DIR, else the shipped weights)")
    token = p.add_mutually_exclusive_group()
    token.add_argument("--token-file", type=Path, metavar="PATH",
                       help="read the bearer token every request but /healthz must carry from this file (mode 600; "
                            "default: $RENDERLOOP_TOKEN_FILE, else $RENDERLOOP_TOKEN)")
    token.add_argument("--token", help="the bearer token itself; every user of the machine sees it in ps, so prefer "
                                       "--token-file or $RENDERLOOP_TOKEN")
    p.add_argument("--allowed-host", action="append", default=[], metavar="NAME",
                   help="a Host header name to serve besides the loopback names (repeatable; '*' for any)")
    p.add_argument("--cors-origin", action="append", default=[], metavar="ORIGIN",
                   help="a web origin allowed to call the API from a browser (repeatable; default: none)")
    p.add_argument("--max-bundle-mb", type=int, default=MAX_BUNDLE_BYTES // 2**20,
                   help=f"largest uploaded scene bundle, uncompressed (default {MAX_BUNDLE_BYTES // 2**20} MiB)")
    p.add_argument("--max-bundle-files", type=int, default=MAX_BUNDLE_FILES,
                   help=f"most files in one bundle (default {MAX_BUNDLE_FILES})")
    p.add_argument("--max-job-memory-gb", type=float, default=SERVICE_LIMITS.max_memory_bytes / 2**30,
                   help="refuse jobs whose estimated memory is over this (default "
                        f"{SERVICE_LIMITS.max_memory_bytes / 2**30:g} GiB)")
    p.add_argument("--keep-days", type=float, default=None,
                   help="remove finished jobs (record and files) this many days after they end (default: keep)")
    p.add_argument("--max-disk-gb", type=float, default=None,
                   help="keep the data folder under this size by removing the oldest finished jobs; a submit that "
                        "finds it full of queued and running jobs gets 507 (default: no cap)")
    p.add_argument("--max-queued", type=int, default=int(os.environ.get(MAX_QUEUED_ENV) or DEFAULT_MAX_QUEUED),
                   help="queued jobs at most, all clients together; beyond: 429 with Retry-After "
                        f"(default: ${MAX_QUEUED_ENV}, else {DEFAULT_MAX_QUEUED})")
    p.add_argument("--max-queued-per-client", type=int,
                   default=int(os.environ.get(MAX_QUEUED_PER_CLIENT_ENV) or DEFAULT_MAX_QUEUED_PER_CLIENT),
                   help="queued jobs at most per client (its bearer token, else its address); beyond: 429 "
                        f"(default: ${MAX_QUEUED_PER_CLIENT_ENV}, else {DEFAULT_MAX_QUEUED_PER_CLIENT})")
    p.add_argument("--insecure-no-auth", action="store_true",
                   help="allow binding a non-loopback address without a token")
    add_edge_arguments(p)
    add_scene_check_arguments(p)
    p.set_defaults(handler=run_serve)


def add_edge_arguments(p) -> None:
    """How the server holds connections (service/api/edge.py, service/api/streams.py)."""
    edge = p.add_argument_group("connections")
    edge.add_argument("--header-timeout", type=float, default=HEADER_TIMEOUT_SECONDS, metavar="S",
                      help=f"close a connection whose request headers are not complete after S seconds "
                           f"(default {HEADER_TIMEOUT_SECONDS:g})")
    edge.add_argument("--keep-alive-timeout", type=int, default=KEEP_ALIVE_SECONDS, metavar="S",
                      help=f"close an idle keep-alive connection after S seconds (default {KEEP_ALIVE_SECONDS})")
    edge.add_argument("--max-connections", type=int, default=MAX_CONNECTIONS, metavar="N",
                      help=f"open connections at most; beyond: 503, and the longest-idle connection is closed "
                           f"first (default {MAX_CONNECTIONS})")
    edge.add_argument("--max-event-streams", type=int, default=MAX_STREAMS_PER_CLIENT, metavar="N",
                      help=f"open event streams per client address; beyond: 429 (default {MAX_STREAMS_PER_CLIENT})")


def serve_edge(args) -> EdgeSettings:
    if not args.header_timeout > 0 or args.keep_alive_timeout < 1:
        raise CliError("--header-timeout must be > 0 and --keep-alive-timeout >= 1")
    if args.max_connections < 2 or args.max_event_streams < 1:
        raise CliError("--max-connections must be >= 2 and --max-event-streams >= 1")
    return EdgeSettings(header_timeout=args.header_timeout, keep_alive_timeout=args.keep_alive_timeout,
                        max_connections=args.max_connections)


def serve_token(args) -> str | None:
    """--token (warned about: `ps` shows it), --token-file, $RENDERLOOP_TOKEN_FILE, $RENDERLOOP_TOKEN."""
    if args.token:
        print("renderloop: warning: --token is visible to every user of this machine (ps, /proc); "
              "use --token-file PATH or $RENDERLOOP_TOKEN", file=sys.stderr)
        return args.token
    path = args.token_file or (Path(os.environ[TOKEN_FILE_ENV]) if os.environ.get(TOKEN_FILE_ENV) else None)
    try:
        return read_token_file(path) if path is not None else os.environ.get(TOKEN_ENV) or None
    except TokenFileError as exc:
        raise CliError(str(exc)) from exc


def serve_security(args) -> SecuritySettings:
    """Refuse to expose an unauthenticated server: a non-loopback bind needs a token."""
    token = serve_token(args)
    if not is_loopback(args.host) and not token and not args.insecure_no_auth:
        raise CliError(f"binding {args.host} exposes the service: give --token-file (or RENDERLOOP_TOKEN), "
                       "or --insecure-no-auth if something in front of it authenticates")
    hosts = list(LOOPBACK_HOSTS) + list(args.allowed_host)
    if not is_loopback(args.host) and args.host not in ("0.0.0.0", "::"):
        hosts.append(args.host)
    return SecuritySettings(token=token, allowed_hosts=tuple(hosts), cors_origins=tuple(args.cors_origin),
                            max_streams_per_client=args.max_event_streams)


def add_scene_check_arguments(p) -> None:
    """Limits of the child process that checks an uploaded scene at submit (service/render/scene_probe.py)."""
    limits = ProbeLimits.from_env()
    checks = p.add_argument_group("untrusted uploads")
    checks.add_argument("--scene-check-memory-mb", type=float, default=limits.memory_bytes / 2**20, metavar="MB",
                        help="memory a scene's check may use (flattening, parsing, loading it in a child process); "
                             f"beyond: 422 (default ${MEMORY_ENV}, else {limits.memory_bytes // 2**20})")
    checks.add_argument("--scene-check-seconds", type=float, default=limits.seconds, metavar="S",
                        help=f"time a scene's check may take; beyond: 422 (default ${SECONDS_ENV}, else {limits.seconds:g})")
    checks.add_argument("--trust-uploads", action="store_true",
                        help="allow --concurrency (the thread backend: no memory cap per job) on a non-loopback "
                             "--host; only when everyone who can submit a job is trusted")


def refuse_untrusted_threads(host: str, workers: WorkerSettings, trust_uploads: bool) -> None:
    """The thread backend renders in the server process with no memory cap per job (a 10⁵-sphere
    job took 8.4 GB there): only for trusted submitters, so not on a reachable address unless said."""
    if workers.concurrency and not is_loopback(host) and not trust_uploads:
        raise CliError(f"--concurrency (the in-process thread backend) bounds no job's memory, so one upload can take "
                       f"the server down; on {host} use the Ray backend (--workers N), or --trust-uploads if everyone "
                       "who can submit is trusted")


def scene_check_limits(args) -> ProbeLimits:
    if not (args.scene_check_memory_mb > 0 and args.scene_check_seconds > 0):
        raise CliError("--scene-check-memory-mb and --scene-check-seconds must be > 0")
    return ProbeLimits(memory_bytes=int(args.scene_check_memory_mb * 2**20), seconds=args.scene_check_seconds)


def run_serve(args) -> int:
    from service.api.serve import serve, worker_settings_from_env  # uvicorn, the app, the loop: only when serving

    if not 0 < args.port < 65536:
        raise CliError(f"--port must be in 1..65535 (got {args.port})")
    for name in ("concurrency", "workers"):
        if getattr(args, name) is not None and getattr(args, name) < 1:
            raise CliError(f"--{name} must be >= 1")
    explicit = args.concurrency is not None or args.workers is not None or args.ray_address
    # No flag: $RENDERLOOP_CONCURRENCY / $RENDERLOOP_WORKERS / $RENDERLOOP_RAY_ADDRESS, else local Ray.
    workers = (WorkerSettings(concurrency=args.concurrency, workers=args.workers, ray_address=args.ray_address,
                              insecure_ray=args.insecure_ray)
               if explicit else replace(worker_settings_from_env(), insecure_ray=args.insecure_ray))
    if workers.ray_address and not workers.insecure_ray and cluster_auth_problem() is not None:
        raise CliError(cluster_auth_problem())
    security, edge = serve_security(args), serve_edge(args)
    if args.max_bundle_mb < 1 or args.max_bundle_files < 1:
        raise CliError("--max-bundle-mb and --max-bundle-files must be >= 1")
    limits = BundleLimits(max_bytes=args.max_bundle_mb * 2**20, max_files=args.max_bundle_files)
    if not args.max_job_memory_gb > 0:
        raise CliError("--max-job-memory-gb must be > 0")
    job_limits = replace(SERVICE_LIMITS, max_memory_bytes=args.max_job_memory_gb * 2**30)
    for name in ("keep_days", "max_disk_gb"):
        if getattr(args, name) is not None and not getattr(args, name) > 0:
            raise CliError(f"--{name.replace('_', '-')} must be > 0")
    retention = Retention(keep_days=args.keep_days,
                          max_disk_bytes=args.max_disk_gb * 2**30 if args.max_disk_gb else None)
    if args.db and not is_postgres_url(args.db):
        raise CliError(f"--db must be a postgresql:// URL (got {without_password(args.db)!r})")
    if args.max_queued < 1 or args.max_queued_per_client < 1:
        raise CliError("--max-queued and --max-queued-per-client must be >= 1")
    quotas = Quotas(max_queued=args.max_queued, max_queued_per_client=args.max_queued_per_client)
    refuse_untrusted_threads(args.host, workers, args.trust_uploads)
    scene_checks = scene_check_limits(args)
    auth = " -H 'authorization: Bearer $RENDERLOOP_TOKEN'" if security.token else ""
    jobs = f", jobs: {without_password(args.db)}" if args.db else ""
    print(f"renderloop serving on http://{args.host}:{args.port}  (data: {args.data_dir}{jobs})")
    print(f"the page: http://{args.host}:{args.port}/  (jobs run on: {workers.describe()})")
    print(f"try: curl -X POST http://{args.host}:{args.port}/jobs{auth} -H 'content-type: application/json' "
          "-d '{\"scene\": \"cornell-box\", \"width\": 64, \"height\": 64, \"max_iterations\": 3}'")
    try:
        serve(args.host, args.port, args.data_dir, workers, networks=load_cli_networks(args.weights),
              security=security, bundle_limits=limits, job_limits=job_limits, retention=retention, db_url=args.db,
              edge=edge, quotas=quotas, scene_checks=scene_checks)
    except StoreUnavailable as exc:
        raise CliError(str(exc)) from exc
    return 0


# -- main -------------------------------------------------------------------------------------

def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="renderloop", description=DESCRIPTION)
    sub = parser.add_subparsers(dest="command", required=True)
    add_render_parser(sub)
    add_serve_parser(sub)
    for module in (dataset_command, train_command, denoise_command):
        module.add_parser(sub)
    client_command.add_parsers(sub)
    # The measurement wing (bench/) is not part of the product: `main` hands `renderloop bench …`
    # to it before parsing; this entry only lists the command in --help.
    sub.add_parser("bench", help="measure and write reports (renderloop bench --help)")
    return parser


# Exception types of modules a command may load, that describe bad input rather than a bug.
# Only those of modules already imported are looked up: an error of a module the command never
# loaded cannot have been raised, and importing Mitsuba just to print `renderloop: error:` cost
# seconds per error line.
LAZY_USER_ERRORS = (("models.checkpoint", "CheckpointError"), ("service.client", "RenderloopError"),
                    ("service.dataset.build", "DatasetError"), ("service.exr", "ExrError"),
                    ("service.render.runtime", "RuntimeSetupError"), ("service.render.scenes", "SceneError"),
                    ("service.scene_upload", "SceneUploadError"))


def user_errors() -> tuple[type[BaseException], ...]:
    """Exception types that describe bad input rather than a bug."""
    loaded = tuple(getattr(sys.modules[module], name) for module, name in LAZY_USER_ERRORS if module in sys.modules)
    return (CliError, JobOptionError, FileNotFoundError, LoopSpecError, TimeoutError, BenchNotInstalled, *loaded)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    keep_freed_memory()   # before any thread or large array: every command's iterations reuse pages
    try:
        if argv[:1] == ["bench"]:
            return load_bench_main()(argv[1:])   # bench/: heavy (imported only now), and only in a checkout
        args = build_parser().parse_args(argv)
        return args.handler(args)
    except KeyboardInterrupt:
        print("renderloop: interrupted", file=sys.stderr)
        return 130
    except user_errors() as exc:
        print(f"renderloop: error: {exc}", file=sys.stderr)
        return EXIT_USAGE


if __name__ == "__main__":
    sys.exit(main())
