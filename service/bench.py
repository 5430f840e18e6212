"""`renderloop bench --sampler | --models | --denoiser`: measured reports written to docs/.

Every report states the command, the machine and the date, and quotes ratios measured side
by side in the same process (the machines are shared and noisy).
"""
from __future__ import annotations

import datetime as _dt
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

from service.loop_bench import add_arguments as add_loop_arguments


def add_parser(sub) -> None:
    p = sub.add_parser("bench", help="measure and write reports to docs/")
    p.add_argument("--sampler", action="store_true", help="renderer samples/s vs mi.render at equal samples")
    p.add_argument("--models", action="store_true", help="denoiser / λ tail forward time and memory")
    p.add_argument("--memory", action="store_true",
                   help="peak RSS of one 1024² x 64 spp render pass (chunked wavefront) in a fresh process")
    p.add_argument("--denoiser", action="store_true", help="denoiser quality on held-out scenes (needs --data)")
    p.add_argument("--data", type=Path, help="data set with a held-out split (for --denoiser)")
    p.add_argument("--size", type=int, default=256, help="image side for --sampler (default 256)")
    p.add_argument("--spp", type=int, default=64, help="samples per pixel for --sampler (default 64)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("-o", "--out", type=Path, default=Path("docs"))
    add_loop_arguments(p)  # --loop [--quick] --weights --cache
    p.set_defaults(handler=run_bench)


def machine_line() -> str:
    return (f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
            f"{_dt.date.today().isoformat()}")


def command_line() -> str:
    return "renderloop " + " ".join(sys.argv[1:])


def bench_sampler(size: int, spp: int, repeats: int) -> dict:
    """Interleaved runs of mi.render and render_samples on the Cornell box at equal samples."""
    from service.render.framebuffer import FrameBuffer
    from service.render.renderer import render_samples
    from service.render.runtime import active_variant, mitsuba
    from service.render.scenes import load_scene

    mi = mitsuba()
    scene = load_scene("cornell-box", width=size, height=size)
    counts = np.full((size, size), spp)
    # One untimed run of each first: kernels are compiled (and cached) on first use.
    np.asarray(mi.render(scene, spp=spp))
    render_samples(scene, counts, FrameBuffer.empty(size, size))
    ours, theirs = [], []
    for rep in range(repeats):
        t0 = time.perf_counter()
        np.asarray(mi.render(scene, spp=spp, seed=rep))
        theirs.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        render_samples(scene, counts, FrameBuffer.empty(size, size), seed=rep)
        ours.append(time.perf_counter() - t0)
    samples = size * size * spp
    ratios = [t / o for t, o in zip(theirs, ours)]
    return {"variant": active_variant(), "size": size, "spp": spp, "samples": samples,
            "mi_render_s": float(np.median(theirs)), "ours_s": float(np.median(ours)),
            "mi_render_msps": samples / np.median(theirs) / 1e6, "ours_msps": samples / np.median(ours) / 1e6,
            "ratio": float(np.median(ratios)), "ratios": ratios}


def write_sampler_report(result: dict, out: Path) -> Path:
    path = out / "sampler.md"
    out.mkdir(parents=True, exist_ok=True)
    path.write_text(f"""# Renderer throughput vs `mi.render`

Command: `{command_line()}`
Machine: {machine_line()}; variant `{result['variant']}`.

Cornell box {result['size']}², {result['spp']} spp ({result['samples']:,} samples), runs interleaved,
median of {len(result['ratios'])}. Ours includes the first-hit AOVs (albedo, normal, depth) that
`mi.render` does not compute, and accumulates sum and sum of squares per pixel.

| renderer | seconds | M samples/s |
|---|---:|---:|
| `mi.render` | {result['mi_render_s']:.2f} | {result['mi_render_msps']:.2f} |
| `render_samples` (per-pixel counts) | {result['ours_s']:.2f} | {result['ours_msps']:.2f} |

Throughput ratio ours / `mi.render`: **{result['ratio']:.2f}×** (per run: {', '.join(f'{r:.2f}' for r in result['ratios'])}; target ≥ 0.9×).
""")
    return path


# Run in a child process so its peak RSS is the render pass's alone (ru_maxrss of children).
MEMORY_PROBE = """
import numpy as np, sys
from service.render.framebuffer import FrameBuffer
from service.render.renderer import render_samples
from service.render.scenes import load_scene
size, spp = int(sys.argv[1]), int(sys.argv[2])
scene = load_scene("cornell-box", width=size, height=size)
result = render_samples(scene, np.full((size, size), spp), FrameBuffer.empty(size, size))
print(result.samples, result.chunks, f"{result.seconds:.1f}")
"""


def bench_memory(size: int = 1024, spp: int = 64) -> dict:
    import resource
    import subprocess

    out = subprocess.run([sys.executable, "-c", MEMORY_PROBE, str(size), str(spp)],
                         capture_output=True, text=True, check=True).stdout.split()
    peak_kb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss  # Linux reports KiB
    return {"size": size, "spp": spp, "samples": int(out[0]), "chunks": int(out[1]), "seconds": float(out[2]),
            "peak_rss_gb": peak_kb / 2**20}


def write_memory_report(result: dict, out: Path) -> Path:
    path = out / "memory.md"
    out.mkdir(parents=True, exist_ok=True)
    path.write_text(f"""# Memory of one large render pass

Command: `{command_line()}`
Machine: {machine_line()}.

Cornell box {result['size']}² × {result['spp']} spp = {result['samples']:,} samples in {result['chunks']} chunks
of at most 2²² lanes, rendered by `render_samples` in a fresh process: **peak RSS
{result['peak_rss_gb']:.2f} GB** (whole process: Python, Mitsuba, the frame buffer), {result['seconds']:.1f} s.
""")
    return path


def run_bench(args) -> int:
    if args.loop:
        from service.loop_bench import run_loop_command

        return run_loop_command(args)
    if args.memory:
        result = bench_memory()
        print(f"memory: peak RSS {result['peak_rss_gb']:.2f} GB; wrote {write_memory_report(result, args.out)}")
    if not (args.sampler or args.models or args.denoiser or args.memory):
        args.sampler = True
    if args.sampler:
        result = bench_sampler(args.size, args.spp, args.repeats)
        print(f"sampler: ours {result['ours_msps']:.2f} M samples/s, mi.render {result['mi_render_msps']:.2f}"
              f" → ratio {result['ratio']:.2f}x; wrote {write_sampler_report(result, args.out)}")
    if args.models:
        from models.bench import main as models_bench

        models_bench([])   # the defaults; `python -m models.bench --help` has the options
    if args.denoiser:
        from service.quality import run_quality_report

        if args.data is None:
            print("renderloop bench: error: --denoiser needs --data DIR with a held-out split", file=sys.stderr)
            return 2
        weights = {} if args.weights is None else {"weights_dir": args.weights}
        print(f"wrote {run_quality_report(args.data, args.out, **weights)}")
    return 0
