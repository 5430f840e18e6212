"""CPU speed and memory of the default denoiser: `python -m bench.models_report`.

Timing: median wall time of `repeats` runs after one warm-up, under torch.inference_mode,
plus the process CPU time of the same runs. On a shared machine wall time includes waiting
for the cores; with one thread, CPU time is close to what the run takes on an idle core.
Memory: torch's CPU allocator is invisible to tracemalloc, so each case runs in a fresh
spawned process and reports the growth of the process's peak resident set size
(resource.getrusage ru_maxrss) caused by the timed runs, on top of the model and inputs
already built. This counts every allocation (tensors, oneDNN scratch, allocator slack) but
is only as fine as the OS page accounting: treat it as ±a few MB.
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import resource
import statistics
import time
from dataclasses import dataclass, replace
from pathlib import Path

import torch

from bench.common import fill, pinned_torch_threads, provenance
from bench.lambda_edit import LAMBDA_EDIT_SIZE, LambdaEditTiming, lambda_edit_section, measure_lambda_edit
from models.checkpoint import load_checkpoint, read_checkpoint, stored_config
from models.denoiser import Denoiser, DenoiserConfig
from models.frames import FrameTensors
from service.loop.denoise_frame import denoise_frame, prepare_frame
from service.loop.oidn import oidn_tensor

# single-frame: no temporal, no pyramid (KPCN); multi-scale: 3 levels, one frame; temporal-3:
# the full default model on a 3-frame window; lambda-tail(-map): apply() alone on a cached
# temporal-3 prepare, with a global λ / a per-pixel λ map; oidn: Intel Open Image Denoise alone
# on one frame (its own threads), the yardstick; window-3: the checkpoint's own config on a
# 3-frame window as a sequence job runs it (a single-frame network pools the window first,
# models.accumulation). With `oidn_candidate` every full case includes the OIDN call the service
# makes for the candidate image (what a denoise costs the product).
CASES = ("single-frame", "multi-scale", "temporal-3", "lambda-tail", "lambda-tail-map", "oidn", "window-3")


def _frame(h: int, w: int, gen: torch.Generator) -> FrameTensors:
    r = lambda c: torch.rand(1, c, h, w, generator=gen)
    return FrameTensors(color=r(3) * 4, variance=r(3), albedo=r(3), normal=r(3) * 2 - 1,
                        depth=r(1), motion=(r(2) - 0.5) * 4)


def _case(name: str, size: int, repeats: int, threads: int, queue, base: DenoiserConfig) -> None:
    torch.set_num_threads(threads)
    torch.manual_seed(0)
    gen = torch.Generator().manual_seed(0)
    # The temporal cases time the checkpoint's architecture with its temporal extractor on, also
    # when the checkpoint is a single-frame network (speed does not depend on trained weights;
    # candidate features are single-frame only, DenoiserConfig.candidate_features).
    cfg = {"single-frame": replace(base, temporal=False, multiscale=False),
           "multi-scale": replace(base, temporal=False), "window-3": base}.get(
        name, replace(base, temporal=True))
    model = Denoiser(cfg).eval()
    window = [_frame(size, size, gen) for _ in range(3 if cfg.temporal or name == "window-3" else 1)]
    center = len(window) // 2
    with torch.inference_mode():
        if name == "window-3":
            def run():
                filtered, at = model.filtered_window(window, center)
                return denoise_frame(model, filtered, at)
        elif name == "oidn":
            run = lambda: oidn_tensor(window[center])
        elif name.startswith("lambda-tail"):
            cache = prepare_frame(model, window, center).cache
            lam = torch.rand(1, 1, size, size, generator=gen) * 9 + 1 if name.endswith("map") else 4.0
            run = lambda: model.apply(cache, lam)
        else:
            run = lambda: denoise_frame(model, window, center)
        run()                                               # warm-up (oneDNN primitive caches)
        rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        times, cpu = [], []
        for _ in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            run()
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    queue.put({"model": name, "size": size, "threads": threads, "load_avg_1min": os.getloadavg()[0],
               "ms_median": 1e3 * statistics.median(times),
               "ms_min": 1e3 * min(times), "cpu_ms_median": 1e3 * statistics.median(cpu),
               "peak_rss_growth_mb": (rss1 - rss0) / 1024, "peak_rss_mb": rss1 / 1024})


def benchmark_models(sizes=(256, 512), repeats: int = 3, threads: int = 2, cases=CASES,
                     config: DenoiserConfig | None = None) -> list[dict]:
    """One dict per (case, size): model, size, threads, load_avg_1min (the machine's load
    when the case finished: other processes share the cores), ms_median, ms_min, cpu_ms_median (process CPU time),
    peak_rss_growth_mb, peak_rss_mb."""
    ctx = mp.get_context("spawn")
    rows = []
    for size in sizes:
        for name in cases:
            queue = ctx.Queue()
            proc = ctx.Process(target=_case, args=(name, size, repeats, threads, queue, config or DenoiserConfig()))
            proc.start()
            rows.append(queue.get())
            proc.join()
    return rows


def write_models_report(rows: list[dict], config: DenoiserConfig, out: Path,
                        lambda_edit: LambdaEditTiming | None = None) -> Path:
    """docs/models-speed.md: this run's table (and the λ edit at 2 MP), with the command, machine and date."""
    table = "\n".join(
        f"| {r['model']} | {r['size']}² | {r['threads']} | {r['ms_median']:.0f} | {r['ms_min']:.0f} | "
        f"{r['cpu_ms_median']:.0f} | {r['peak_rss_growth_mb']:.0f} | {r['load_avg_1min']:.1f} |" for r in rows)
    path = out / "models-speed.md"
    out.mkdir(parents=True, exist_ok=True)
    path.write_text(fill("models.md", provenance=provenance(), config=config, table=table,
                         lambda_edit=lambda_edit_section(lambda_edit)))
    return path


@dataclass(frozen=True)
class ThreadTiming:
    size: int
    repeats: int
    ms_median: dict[int, float]  # torch threads → median wall ms of one single-frame denoise


def denoise_ms_by_threads(denoiser: Denoiser, size: int, thread_counts: tuple[int, ...] = (1, 2),
                          repeats: int = 5) -> ThreadTiming:
    """Median wall time of one single-frame forward pass of `denoiser` at size² per torch thread
    count, in this process, interleaved so the machine's load hits every count alike. The loop
    report runs every timed network call with the faster count (bench.loop_report.choose_torch_threads)."""
    gen = torch.Generator().manual_seed(0)
    window = [_frame(size, size, gen)]
    times: dict[int, list[float]] = {t: [] for t in thread_counts}
    with torch.inference_mode():
        # a denoiser with the OIDN candidate takes OIDN's image as an input: fetched once by the
        # one denoise path (service.loop.denoise_frame), untimed
        candidate = prepare_frame(denoiser, window, 0).candidate
        for threads in thread_counts:  # warm-up per count: oneDNN builds primitives per thread count
            with pinned_torch_threads(threads):
                denoiser(window, 0, 1.0, candidate)
        for _ in range(repeats):
            for threads in thread_counts:
                with pinned_torch_threads(threads):
                    t0 = time.perf_counter()
                    denoiser(window, 0, 1.0, candidate)
                    times[threads].append(time.perf_counter() - t0)
    return ThreadTiming(size, repeats, {t: 1e3 * statistics.median(v) for t, v in times.items()})


def versus_oidn(config: DenoiserConfig, size: int = 512, repeats: int = 7, threads: int = 2) -> dict[str, float]:
    """Wall ms (minimum and median of `repeats`) of OIDN alone and of one frame through a denoiser
    of `config` (λ = 1, with the OIDN call it needs when `oidn_candidate`), its network part alone
    and its λ tail, interleaved round by round in this process so the machine's load hits every
    case alike: on a shared host the minimum is the figure least disturbed by other work."""
    gen = torch.Generator().manual_seed(0)
    frame = _frame(size, size, gen)
    model = Denoiser(replace(config, temporal=False)).eval()
    prepared = prepare_frame(model, [frame], 0)   # the candidate it needs, fetched by the one denoise path
    candidate, cache = prepared.candidate, prepared.cache
    cases = {
        "oidn": lambda: oidn_tensor(frame),
        "denoise (with its OIDN call)": lambda: denoise_frame(model, [frame], 0),
        "network only": lambda: model([frame], 0, 1.0, candidate),
        "lambda tail": lambda: model.apply(cache, 4.0),
    }
    times: dict[str, list[float]] = {name: [] for name in cases}
    with torch.inference_mode(), pinned_torch_threads(threads):
        for run in cases.values():
            run()                                               # warm-up
        for _ in range(repeats):
            for name, run in cases.items():
                t0 = time.perf_counter()
                run()
                times[name].append(1e3 * (time.perf_counter() - t0))
    return {f"{name} {stat}": f(v) for name, v in times.items() for stat, f in (("min", min), ("median", statistics.median))}


def main(argv: list[str] | None = None, out: Path | None = None) -> Path | None:
    """python -m bench.models_report [SIZE ...] [--threads T] [--repeats R] [--width W] [--spatial-blocks B] [-o DIR]"""
    parser = argparse.ArgumentParser(description="CPU benchmark of the default denoiser")
    parser.add_argument("sizes", nargs="*", type=int, default=[256, 512])
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--width", type=int, default=DenoiserConfig.width)
    parser.add_argument("--spatial-blocks", type=int, default=DenoiserConfig.spatial_blocks)
    parser.add_argument("--config-from", type=Path, metavar="CHECKPOINT",
                        help="time the architecture a checkpoint holds (e.g. models/weights/denoiser.pt)")
    parser.add_argument("--versus-oidn", action="store_true",
                        help="one frame through the denoiser beside OIDN, interleaved in one process (prints only)")
    parser.add_argument("--lambda-edit-size", type=int, nargs=2, default=LAMBDA_EDIT_SIZE, metavar=("W", "H"),
                        help="the λ edit's image size (default 1920 1080): the tail on the --config-from "
                             "checkpoint's weights, and PUT /jobs/{id}/lambda against a real server on its folder's")
    parser.add_argument("--no-lambda-edit", action="store_true", help="skip the λ edit measurement")
    parser.add_argument("--no-http", action="store_true", help="the λ edit's tail only, no server")
    parser.add_argument("-o", "--out", type=Path, default=out, help="write DIR/models-speed.md")
    args = parser.parse_args(argv)
    config = DenoiserConfig(width=args.width, spatial_blocks=args.spatial_blocks)
    if args.config_from is not None:
        config = stored_config(read_checkpoint(args.config_from), args.config_from)
    if args.versus_oidn:
        for size in args.sizes:
            for name, ms in versus_oidn(config, size, args.repeats, args.threads).items():
                print(f"{size}² {args.threads} thread(s) {name}: {ms:.0f} ms")
        return None
    rows = benchmark_models(tuple(args.sizes), args.repeats, args.threads, config=config)
    for r in rows:
        print(f"{r['model']} {r['size']}² {r['threads']} thread(s): {r['ms_median']:.0f} ms median, "
              f"{r['peak_rss_growth_mb']:.0f} MB peak RSS growth")
    edit = None if args.no_lambda_edit else _lambda_edit(args, config)
    return write_models_report(rows, config, args.out, edit) if args.out is not None else None


def _lambda_edit(args: argparse.Namespace, config: DenoiserConfig) -> LambdaEditTiming:
    """The λ edit on the checkpoint's own weights when --config-from names one (and the server on
    its folder), else on an untrained network of `config` without the server."""
    checkpoint = args.config_from
    denoiser = load_checkpoint(checkpoint, expected_kind=Denoiser.kind) if checkpoint else Denoiser(config)
    folder = None if args.no_http or checkpoint is None else checkpoint.parent
    edit = measure_lambda_edit(denoiser, folder, tuple(args.lambda_edit_size), max(args.repeats, 7), args.threads)
    print(lambda_edit_section(edit))
    return edit


if __name__ == "__main__":
    main()
