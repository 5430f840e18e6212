"""`renderloop bench --sampler | --models | --denoiser`: measured reports written to docs/.

Every report states the command, the machine and the date, and quotes ratios measured side
by side in the same process (the machines are shared and noisy).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from bench.dev_references import DEFAULT_REFERENCE_DIR, write_references
from bench.loop_report import add_arguments as add_loop_arguments, run_loop_command
from bench.models_report import main as models_bench
from bench.quality_report import run_quality_report
from bench.sampler_report import bench_memory, bench_sampler, write_memory_report, write_sampler_report


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="renderloop bench", description="measure and write reports to docs/")
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
    p.add_argument("--references", action="store_true",
                   help="render the development suite's references (scenes/dev, mi.render as written; use a GPU)")
    p.add_argument("--references-dir", type=Path, default=DEFAULT_REFERENCE_DIR)
    p.add_argument("--reference-spp", type=int, default=None,
                   help="samples per pixel of every reference (default 16384; 65536 for the noisiest scenes)")
    p.add_argument("--only", nargs="+", default=None, metavar="SCENE", help="with --references: these scenes only")
    add_loop_arguments(p)  # --loop [--quick] --weights --cache
    return p


def main(argv: list[str]) -> int:
    return run_bench(build_parser().parse_args(argv))


def run_bench(args) -> int:
    if args.references:
        written = write_references(args.references_dir, spp=args.reference_spp, only=args.only)
        print(f"wrote {len(written)} reference(s) to {args.references_dir}")
        return 0
    if args.loop:
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
        # The defaults (256² and 512², 2 threads); `python -m bench.models_report --help` has the options.
        print(f"wrote {models_bench([], out=args.out)}")
    if args.denoiser:
        if args.data is None:
            print("renderloop bench: error: --denoiser needs --data DIR with a held-out split", file=sys.stderr)
            return 2
        weights = {} if args.weights is None else {"weights_dir": args.weights}
        print(f"wrote {run_quality_report(args.data, args.out, **weights)}")
    return 0
