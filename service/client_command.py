"""`renderloop submit|jobs|status|cancel|download|delete`: arguments → service.client.RenderloopClient
against a running server (`renderloop serve`). `submit` takes the job options `render` takes
(service/job_options.py, one function for both). The client (httpx, OpenEXR) is imported when a
command runs, so `renderloop --help` stays light; the client itself resolves the server and
token defaults from the environment."""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path

from service.api.security import TOKEN_FILE_ENV, TokenFileError, read_token_file
from service.job_options import JobOptionError, add_job_options, api_fields, spec_from_args

JOB_COLUMNS = ("ID", "STATE", "ITER", "SPP", "ERROR", "NAME", "CREATED")
STATES = ("queued", "running", "completed", "failed", "canceled")


def add_server_arguments(p) -> None:
    p.add_argument("--server", help="the service's URL (default: $RENDERLOOP_SERVER, else http://127.0.0.1:8000)")
    token = p.add_mutually_exclusive_group()
    token.add_argument("--token", help="bearer token when the server needs one (default: $RENDERLOOP_TOKEN_FILE's "
                                       "file, else $RENDERLOOP_TOKEN); ps shows it, so prefer --token-file")
    token.add_argument("--token-file", type=Path, metavar="PATH", help="read the bearer token from this file")


def add_parsers(sub) -> None:
    add_submit_parser(sub)
    p = sub.add_parser("jobs", help="list the jobs of a running server")
    add_server_arguments(p)
    p.add_argument("--state", choices=STATES)
    p.add_argument("--limit", type=int, default=50, help="newest first, at most this many (default 50)")
    p.set_defaults(handler=run_jobs)
    for verb, help_text, handler in (("status", "print a job's record (JSON)", run_status),
                                     ("cancel", "cancel a queued or running job", run_cancel),
                                     ("delete", "delete a finished job: its record and files", run_delete)):
        p = sub.add_parser(verb, help=help_text)
        p.add_argument("job_id", metavar="ID")
        add_server_arguments(p)
        p.set_defaults(handler=handler)
    p = sub.add_parser("download", help="download a finished job's EXR (one per frame)")
    p.add_argument("job_id", metavar="ID")
    add_server_arguments(p)
    p.add_argument("-o", "--output", type=Path, required=True,
                   help="output EXR path (a sequence gives OUT_0000.exr, …)")
    p.add_argument("--png", action="store_true", help="also write a tonemapped PNG beside each EXR")
    p.set_defaults(handler=run_download)


def add_submit_parser(sub) -> None:
    p = sub.add_parser("submit", help="submit a job to a running server (and wait for its EXR)")
    p.add_argument("scene", help="a built-in scene name (GET /scenes), or a scene XML file or folder: the files the "
                                 "scene references are uploaded, nothing else")
    p.add_argument("--scene", dest="entry", metavar="NAME",
                   help="which scene XML of a folder holding several (NAME or NAME.xml)")
    add_server_arguments(p)
    add_job_options(p, service=True)  # the same options as `renderloop render` (service/job_options.py)
    p.add_argument("--wait", action="store_true", help="follow the job with a progress bar until it ends")
    p.add_argument("-o", "--output", type=Path, help="download the result EXR here when it ends (implies --wait; "
                                                     "a sequence gives OUT_0000.exr, …)")
    p.set_defaults(handler=run_submit)


def client_token(args) -> str | None:
    """--token, --token-file, $RENDERLOOP_TOKEN_FILE; None leaves $RENDERLOOP_TOKEN to the client."""
    if args.token:
        return args.token
    path = args.token_file or (Path(os.environ[TOKEN_FILE_ENV]) if os.environ.get(TOKEN_FILE_ENV) else None)
    try:
        return read_token_file(path) if path is not None else None
    except TokenFileError as exc:
        raise JobOptionError(str(exc)) from exc


def connect(args):
    from service.client import RenderloopClient

    return RenderloopClient(args.server, client_token(args))


def run_submit(args) -> int:
    from service.client import JobDidNotComplete, is_local_scene
    from service.exr import require_exr_path
    from service.scene_upload import plan_upload

    if args.output is not None:
        require_exr_path(args.output)  # as `render` does, before anything is sent
    fields = api_fields(spec_from_args(args, args.scene, default_iterations=None))
    with connect(args) as client:
        if is_local_scene(args.scene):
            upload = plan_upload(args.scene, scene=args.entry, params=fields.get("params"), frames=args.frames,
                                 width=args.width, height=args.height)
            print(f"uploading {len(upload.files)} file(s), {upload.size / 2**20:.2f} MiB: {upload.name}",
                  file=sys.stderr)
            job_id = client.submit_upload(upload, **fields)
        else:
            if args.entry is not None:
                raise JobOptionError("--scene picks a scene XML inside an uploaded folder, not a built-in scene")
            job_id = client.submit(args.scene, **fields)
        print(job_id, flush=True)  # stdout carries the id alone, for scripts: ID=$(renderloop submit …)
        if not (args.wait or args.output):
            return 0
        final = client.wait(job_id)
        if final["state"] != "completed":
            reason = final.get("error") or final.get("stop_reason") or "no reason given"
            raise JobDidNotComplete(f"job {job_id} ended {final['state']}: {reason}")
        print(f"{job_id} completed: {final['iteration']} iterations, {final['spp']:.1f} spp mean, "
              f"stop: {final['stop_reason']}")
        if args.output:
            download_frames(client, job_id, final, args.output, args.png)
    return 0


def download_frames(client, job_id: str, record: dict, output: Path, png: bool) -> None:
    """Every frame's EXR (and a tonemapped PNG beside each with `png`)."""
    from service.exr import frame_path, read_exr
    from service.images import tonemap, write_png

    frames = record["spec"].get("frames", 1)
    for f in range(frames):
        path = client.download(job_id, frame_path(output, f, frames), frame=f)
        print(f"wrote {path}")
        if png:
            print(f"wrote {write_png(path.with_suffix('.png'), tonemap(read_exr(path).color))}")


def run_status(args) -> int:
    with connect(args) as client:
        print(json.dumps(client.status(args.job_id), indent=2))
    return 0


def run_cancel(args) -> int:
    with connect(args) as client:
        record = client.cancel(args.job_id)
    # A queued job is canceled at once; a running one stops after its current wavefront chunk.
    state = record.get("state")
    print(f"{args.job_id} canceled" if state == "canceled" else f"{args.job_id} stopping (was {state})")
    return 0


def run_delete(args) -> int:
    with connect(args) as client:
        client.delete(args.job_id)
    print(f"{args.job_id} deleted")
    return 0


def run_download(args) -> int:
    from service.exr import require_exr_path

    require_exr_path(args.output)
    with connect(args) as client:
        download_frames(client, args.job_id, client.status(args.job_id), args.output, args.png)
    return 0


def job_row(job: dict) -> tuple[str, ...]:
    spec = job.get("spec", {})
    error = job.get("predicted_error")
    return (job["id"], job["state"], str(job["iteration"]), f"{job['spp']:.1f}",
            "-" if error is None else f"{error:.4f}", job.get("name") or str(spec.get("scene", "?")),
            (job.get("created_at") or "")[:19].replace("T", " "))


def format_table(rows: list[tuple[str, ...]]) -> str:
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    return "\n".join("  ".join(cell.ljust(width) for cell, width in zip(row, widths)).rstrip() for row in rows)


def run_jobs(args) -> int:
    with connect(args) as client:
        jobs = client.jobs(state=args.state, limit=args.limit)
    if not jobs:
        print("no jobs")
        return 0
    print(format_table([JOB_COLUMNS] + [job_row(job) for job in jobs]))
    return 0
