"""The λ tail of two trees side by side: an earlier commit's and this working tree's,
on the same 2 MP input, in alternating fresh processes so the host's load hits both alike.

    python -m bench.lambda_edit_ab --before COMMIT [--image RENDER.exr | --size W H] [--rounds 3] [--repeats 5] [--threads 2]

    python -m bench.lambda_edit_ab --before COMMIT --http [--settle] [--backends thread ray] [--size W H] [--requests 6]

`--before` is git-archived into a temporary folder; each round runs one process per tree, which
loads the shipped weights of THIS tree (the same network on both sides), builds the cache from
`--image` (a `renderloop render --no-denoise` EXR with its albedo/normal layers; default random
1920×1080 inputs) and the OIDN candidate, then times `to_image(Denoiser.apply(cache, λ))` —
`repeats` times after a warm-up — for a uniform λ map (a global edit as the service sends it)
and a painted rectangle over the middle third. Printed: each round's medians, then per tree and
case the median of the rounds' medians and their spread (min–max).

With `--http` each round instead runs `http_worker` with each tree (its code on PYTHONPATH, for
the server subprocess too) on each backend: a real `renderloop serve` app, a finished
one-iteration 16-spp cornell-box job of `--size`, then `--requests` PUT /jobs/{id}/lambda back
to back (global value and rectangle alternating, as bench.server.bench_http_lambda sends them),
or with `--settle` each once the previous edit's files are written; printed: p50/p95/max ms per
tree, backend and round.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
CASES = ("uniform map", "rectangle map")


def worker(root: str, image: str, threads: int, repeats: int, size: tuple[int, int] = (1920, 1080)) -> dict[str, float]:
    """In a fresh process: median wall ms of each case with `root`'s models/ and service/."""
    sys.path.insert(0, root)   # the tree under test, before anything imports models or service

    import torch

    from models.checkpoint import load_checkpoint
    from models.frames import FrameTensors
    from service.loop.tensors import to_image
    try:   # the one denoise path (service/loop/denoise_frame.py); a tree from before it fetched the candidate here
        from service.loop.denoise_frame import prepare_frame
        prepare = lambda: prepare_frame(denoiser, [frame], 0).cache   # noqa: E731
    except ImportError:
        from service.loop.oidn import candidate_for
        prepare = lambda: denoiser.prepare([frame], 0, candidate_for(denoiser, frame))   # noqa: E731

    torch.set_num_threads(threads)
    if image:
        from service.exr import read_exr
        from service.exr_denoise import frame_from_exr
        frame = frame_from_exr(Path(image), read_exr(image))
    else:
        gen = torch.Generator().manual_seed(0)
        r = lambda c: torch.rand(1, c, size[1], size[0], generator=gen)
        frame = FrameTensors(color=r(3) * 4, variance=r(3), albedo=r(3), normal=r(3) * 2 - 1, depth=r(1))
    denoiser = load_checkpoint(REPO / "models" / "weights" / "denoiser.pt").eval()
    height, width = frame.color.shape[-2:]
    rectangle = torch.ones(1, 1, height, width)
    rectangle[..., height // 3: 2 * height // 3, width // 3: 2 * width // 3] = 6.0
    maps = dict(zip(CASES, (torch.full((1, 1, height, width), 4.0), rectangle)))
    medians = {}
    with torch.inference_mode():
        cache = prepare()
        for name, lam in maps.items():
            to_image(denoiser.apply(cache, lam))
            times = []
            for _ in range(repeats):
                started = time.perf_counter()
                to_image(denoiser.apply(cache, lam))
                times.append(1e3 * (time.perf_counter() - started))
            medians[name] = statistics.median(times)
    return medians


def run_tree(root: Path, image: Path | None, threads: int, repeats: int, size: tuple[int, int]) -> dict[str, float]:
    command = [sys.executable, str(Path(__file__).resolve()), "--worker", str(root), str(image or ""),
               str(threads), str(repeats), *map(str, size)]
    out = subprocess.run(command, check=True, capture_output=True, text=True, cwd=root).stdout
    return json.loads(out.strip().splitlines()[-1])


def http_worker(size: tuple[int, int], requests: int, weights_dir: str, threads: int, settle: bool) -> dict:
    """In a fresh process whose PYTHONPATH is the tree under test: its server (bench.server's
    running_server) with a finished one-iteration 16-spp cornell-box job, then `requests` PUT
    /jobs/{id}/lambda after one warm-up, a global value and a rectangle alternating, as
    bench.server.bench_http_lambda sends them. `settle`: after each PUT, an untimed GET of
    result.exr (which waits for the edit's files), so no PUT shares the CPU with the writes of
    the one before; otherwise back to back."""
    import httpx
    import numpy as np

    from bench.server import running_server, wait_for_job
    width, height = size
    seconds = []
    with tempfile.TemporaryDirectory(prefix="lambda-ab-http-") as tmp:
        with running_server(Path(tmp) / "data", Path(weights_dir), threads) as url, \
                httpx.Client(base_url=url, timeout=600) as client:
            created = client.post("/jobs", json={"scene": "cornell-box", "width": width, "height": height,
                                                 "max_iterations": 1, "seed": 0})
            created.raise_for_status()
            job_id = created.json()["id"]
            if wait_for_job(client, job_id, timeout=1800)["state"] != "completed":
                raise RuntimeError("the benchmark job did not complete")
            for i in range(requests + 1):
                body = ({"value": 2.0 + (i % 7)} if i % 2 == 0 else
                        {"rects": [{"x": 0, "y": 0, "w": width // 2, "h": height, "value": 10.0 - (i % 5)}]})
                started = time.perf_counter()
                client.put(f"/jobs/{job_id}/lambda", json=body).raise_for_status()
                if i:
                    seconds.append(time.perf_counter() - started)
                if settle:
                    client.get(f"/jobs/{job_id}/result.exr").raise_for_status()
    ms = np.array(seconds) * 1e3
    return {"requests": len(ms), "p50_ms": float(np.percentile(ms, 50)), "p95_ms": float(np.percentile(ms, 95)),
            "max_ms": float(ms.max())}


def run_http(root: Path, backend: str, size: tuple[int, int], requests: int, threads: int, settle: bool) -> dict:
    """http_worker with `root`'s code in a fresh process (and in its server subprocess)."""
    env = {**os.environ, "PYTHONPATH": str(root)}
    env.pop("RENDERLOOP_CONCURRENCY", None)
    if backend == "thread":
        env["RENDERLOOP_CONCURRENCY"] = "1"   # `renderloop serve --concurrency 1`
    command = [sys.executable, str(Path(__file__).resolve()), "--http-worker", *map(str, size), str(requests),
               str(REPO / "models" / "weights"), str(threads), str(int(settle))]
    out = subprocess.run(command, check=True, capture_output=True, text=True, cwd=root, env=env).stdout
    return json.loads(out.strip().splitlines()[-1])


def main_http(args: argparse.Namespace) -> dict[str, dict[str, list[dict]]]:
    results: dict[str, dict[str, list[dict]]] = {"before": {b: [] for b in args.backends},
                                                 "after": {b: [] for b in args.backends}}
    with tempfile.TemporaryDirectory(prefix="lambda-ab-") as folder:
        archive = subprocess.run(["git", "-C", str(REPO), "archive", args.before], check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", folder], input=archive, check=True)
        for round_ in range(args.rounds):
            for backend in args.backends:
                for label, root in (("before", Path(folder)), ("after", REPO)):
                    row = run_http(root, backend, tuple(args.size), args.requests, args.threads, args.settle)
                    results[label][backend].append(row)
                    print(f"round {round_ + 1} {backend} {label}: p50 {row['p50_ms']:.0f} ms, p95 {row['p95_ms']:.0f} ms, "
                          f"max {row['max_ms']:.0f} ms over {row['requests']} requests", flush=True)
    return results


def main(argv: list[str] | None = None) -> dict[str, dict[str, list[float]]]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--before", required=True, help="the earlier commit")
    parser.add_argument("--image", type=Path, default=None)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--size", type=int, nargs=2, default=(1920, 1080), metavar=("W", "H"),
                        help="the random inputs' size without --image; the job's with --http")
    parser.add_argument("--http", action="store_true", help="time PUT /jobs/{id}/lambda against a real server")
    parser.add_argument("--backends", nargs="+", choices=("thread", "ray"), default=["thread", "ray"])
    parser.add_argument("--requests", type=int, default=6)
    parser.add_argument("--settle", action="store_true",
                        help="with --http: each PUT after the last one's files are written (an untimed GET of result.exr)")
    args = parser.parse_args(argv)
    if args.http:
        return main_http(args)
    image = args.image.resolve() if args.image else None
    results: dict[str, dict[str, list[float]]] = {"before": {c: [] for c in CASES}, "after": {c: [] for c in CASES}}
    with tempfile.TemporaryDirectory(prefix="lambda-ab-") as folder:
        archive = subprocess.run(["git", "-C", str(REPO), "archive", args.before], check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", folder], input=archive, check=True)
        for round_ in range(args.rounds):
            for label, root in (("before", Path(folder)), ("after", REPO)):
                medians = run_tree(root, image, args.threads, args.repeats, tuple(args.size))
                for case, ms in medians.items():
                    results[label][case].append(ms)
                print(f"round {round_ + 1} {label}: " + ", ".join(f"{c} {ms:.0f} ms" for c, ms in medians.items()),
                      flush=True)
    for label, cases in results.items():
        for case, ms in cases.items():
            print(f"{label} ({args.before if label == 'before' else 'working tree'}) {case}: median of rounds "
                  f"{statistics.median(ms):.0f} ms, spread {min(ms):.0f}–{max(ms):.0f} ms")
    return results


if __name__ == "__main__":
    if sys.argv[1:2] == ["--http-worker"]:
        width, height, requests, weights, threads, settle = sys.argv[2:8]
        print(json.dumps(http_worker((int(width), int(height)), int(requests), weights, int(threads), settle == "1")))
    elif sys.argv[1:2] == ["--worker"]:
        root, image, threads, repeats, width, height = sys.argv[2:8]
        print(json.dumps(worker(root, image, int(threads), int(repeats), (int(width), int(height)))))
    else:
        main()
