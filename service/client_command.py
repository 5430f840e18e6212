"""`renderloop submit SCENE …` and `renderloop jobs`: arguments → service.client.RenderloopClient
against a running server (`renderloop serve`). The client (httpx, OpenEXR) is imported when a
command runs, so `renderloop --help` stays light; the client itself resolves the server and
token defaults from the environment."""
from __future__ import annotations

from pathlib import Path

from service.loop.spec import LAMBDA_RANGE

JOB_COLUMNS = ("ID", "STATE", "ITER", "SPP", "ERROR", "SCENE", "CREATED")


def add_server_arguments(p) -> None:
    p.add_argument("--server", help="the service's URL (default: $RENDERLOOP_SERVER, else http://127.0.0.1:8000)")
    p.add_argument("--token", help="bearer token when the server needs one (default: $RENDERLOOP_TOKEN)")


def add_parsers(sub) -> None:
    p = sub.add_parser("submit", help="submit a job to a running server (and wait for its EXR)")
    p.add_argument("scene", help="a built-in scene name (GET /scenes), or a scene folder / XML file: "
                                 "its folder is zipped and uploaded")
    add_server_arguments(p)
    p.add_argument("--width", type=int, help="film width in pixels (default: the scene's own; give --height too)")
    p.add_argument("--height", type=int, help="film height in pixels (default: the scene's own)")
    p.add_argument("--iterations", type=int, help="maximum iterations (default: the server's, 4)")
    p.add_argument("--lambda", dest="lam", type=float,
                   help=f"λ in [{LAMBDA_RANGE[0]:g}, {LAMBDA_RANGE[1]:g}] (default 1)")
    p.add_argument("--wait", action="store_true", help="follow the job with a progress bar until it ends")
    p.add_argument("-o", "--output", type=Path, help="download the result EXR here when it ends (implies --wait; "
                                                     "a sequence gives OUT_0000.exr, …)")
    p.set_defaults(handler=run_submit)

    p = sub.add_parser("jobs", help="list the jobs of a running server")
    add_server_arguments(p)
    p.add_argument("--state", choices=("queued", "running", "completed", "failed", "canceled"))
    p.add_argument("--limit", type=int, default=50, help="newest first, at most this many (default 50)")
    p.set_defaults(handler=run_jobs)


def submit_spec(args) -> dict:
    spec = {"width": args.width, "height": args.height, "max_iterations": args.iterations, "lambda": args.lam}
    return {name: value for name, value in spec.items() if value is not None}


def run_submit(args) -> int:
    from service.client import JobDidNotComplete, RenderloopClient
    from service.exr import frame_path

    with RenderloopClient(args.server, args.token) as client:
        job_id = client.submit(args.scene, **submit_spec(args))
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
            frames = final["spec"].get("frames", 1)
            for f in range(frames):
                print(f"wrote {client.download(job_id, frame_path(args.output, f, frames), frame=f)}")
    return 0


def job_row(job: dict) -> tuple[str, ...]:
    spec = job.get("spec", {})
    error = job.get("predicted_error")
    return (job["id"], job["state"], str(job["iteration"]), f"{job['spp']:.1f}",
            "-" if error is None else f"{error:.4f}", str(spec.get("scene", "?")),
            (job.get("created_at") or "")[:19].replace("T", " "))


def format_table(rows: list[tuple[str, ...]]) -> str:
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    return "\n".join("  ".join(cell.ljust(width) for cell, width in zip(row, widths)).rstrip() for row in rows)


def run_jobs(args) -> int:
    from service.client import RenderloopClient

    with RenderloopClient(args.server, args.token) as client:
        jobs = client.jobs(state=args.state, limit=args.limit)
    if not jobs:
        print("no jobs")
        return 0
    print(format_table([JOB_COLUMNS] + [job_row(job) for job in jobs]))
    return 0
