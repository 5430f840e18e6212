"""`renderloop bench …`: which report to measure and write. `add_parser(sub)` registers the
subcommand on the product's CLI; `main(argv)` parses on its own (`python -m bench.cli`)."""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

# Only what the parser needs is imported here: each report module (torch, Ray, matplotlib,
# FastAPI, scipy behind them) is imported by the branch of `run_bench` that runs it, so a
# `renderloop bench --loop` does not pay for the other reports' imports (seconds per process on
# a busy host). The three modes below own flags the parser needs, so `--help` stays complete.
from bench.as_written import add_arguments as add_as_written_arguments
from bench.calibration_ceiling import CEILING_RENDER_RANGE, CEILING_RENDERS
from bench.dev_references import DEFAULT_REFERENCE_DIR, VAL_REFERENCE_DIR
from bench.loop_report import add_arguments as add_loop_arguments
from bench.versus_mitsuba import add_arguments as add_versus_mitsuba_arguments

HELP = "measure and write reports (to ./bench-reports; -o docs regenerates the committed ones)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--sampler", action="store_true", help="renderer samples/s vs mi.render at equal samples")
    p.add_argument("--models", action="store_true", help="denoiser / λ tail forward time and memory → docs/models-speed.md")
    p.add_argument("--memory", action="store_true",
                   help="peak RSS of one 1024² x 64 spp render pass (chunked wavefront) in a fresh process")
    p.add_argument("--denoiser", action="store_true",
                   help="denoiser quality on held-out scenes (needs --data), or with --suite dev on scenes/dev vs OIDN")
    p.add_argument("--data", type=Path, help="data set with a held-out split (for --denoiser)")
    p.add_argument("--size", type=int, default=None, help="image side for --sampler (default 256) or --as-written (128)")
    p.add_argument("--spp", type=int, default=None, help="samples per pixel for --sampler (default 64) or --as-written (128)")
    p.add_argument("--repeats", type=int, default=3)
    # Not docs/: a run inside the repository must not overwrite the committed reports by default.
    p.add_argument("-o", "--out", type=Path, default=Path("bench-reports"),
                   help="folder the reports go to (default ./bench-reports; the committed ones live in docs/)")
    p.add_argument("--references", action="store_true",
                   help="render the development suite's references (scenes/dev, mi.render as written; use a GPU), "
                        "or with --suite val the validation scenes' (scenes/val)")
    p.add_argument("--references-dir", type=Path, default=None,
                   help=f"default {DEFAULT_REFERENCE_DIR.relative_to(DEFAULT_REFERENCE_DIR.parents[2])}, "
                        f"or {VAL_REFERENCE_DIR.relative_to(VAL_REFERENCE_DIR.parents[2])} with --suite val")
    p.add_argument("--reference-spp", type=int, default=None,
                   help="samples per pixel of every reference (default 16384; 65536 for the noisiest scenes)")
    p.add_argument("--only", nargs="+", default=None, metavar="SCENE",
                   help="with --references, --dev-suite or --calibration: these development scenes only")
    p.add_argument("--suite-spp", type=int, nargs="+", default=None, metavar="SPP",
                   help="with --denoiser --suite dev: these sample counts only (default 16 64 256)")
    p.add_argument("--dev-suite", action="store_true",
                   help="KPCN vs OIDN at 16 spp and the loop vs uniform + OIDN at 128 spp on scenes/dev → docs/dev-suite.md")
    p.add_argument("--calibration", action="store_true",
                   help="predicted vs true error per iteration and where --target-error stops, on scenes/dev → "
                        "calibration.md (with --suite val: scenes/val → calibration-val.md)")
    p.add_argument("--ceiling-renders", type=int, default=CEILING_RENDERS, metavar="K",
                   help=f"with --calibration: K renders per scene at the first spp for the repeatable-error ceiling "
                        f"of the per-pixel Spearman ({CEILING_RENDER_RANGE[0]}–{CEILING_RENDER_RANGE[1]}, 0: not "
                        f"measured; default {CEILING_RENDERS})")
    p.add_argument("--fit-scale", type=Path, default=None, metavar="DIR",
                   help="with --calibration --suite val: also write the error network of --weights to DIR with "
                        "the output scale that makes its median predicted ÷ true error 1 on those scenes, and the "
                        "change scale that does the same for the mean calibrated by the image's change")
    p.add_argument("--lambda-edit", action="store_true",
                   help="a λ edit at 1920×1080: the tail from cached features, and PUT /jobs/{id}/lambda → the new "
                        "preview over HTTP on both job backends of a real server, split into parts → lambda-edit.md")
    p.add_argument("--lambda-requests", type=int, default=20, metavar="N",
                   help="with --lambda-edit: timed edits per backend (default 20)")
    p.add_argument("--scale", action="store_true",
                   help="Ray workers: 8 jobs on 1 vs 2 workers, Ray vs in-process overhead per iteration, a 5-frame "
                        "sequence on 1 vs 2 workers → scale.md")
    add_loop_arguments(p)  # --loop [--quick] --weights --cache
    add_versus_mitsuba_arguments(p)  # --versus-mitsuba --megapixels --max-spp --scenes
    add_as_written_arguments(p)  # --as-written --tutorials --seeds


def add_parser(sub) -> None:
    """Register `bench` on the product CLI's subparsers."""
    p = sub.add_parser("bench", help=HELP, description=HELP)
    add_arguments(p)
    p.set_defaults(handler=run_bench)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="renderloop bench", description=HELP)
    add_arguments(p)
    return p


def main(argv: list[str]) -> int:
    return run_bench(build_parser().parse_args(argv))


def run_bench(args: argparse.Namespace) -> int:
    if args.film_scale < 1:  # --references and --loop
        print("renderloop bench: error: --film-scale must be >= 1", file=sys.stderr)
        return 2
    if args.references:
        from bench.dev_references import SUITES, scaled_reference_dir, write_references
        suite = SUITES["val" if args.suite == "val" else "dev"]
        default = suite.references if args.film_scale == 1 else scaled_reference_dir(args.cache, args.film_scale)
        folder = args.references_dir or default
        written = write_references(folder, spp=args.reference_spp, only=args.only, root=suite.root,
                                   film_scale=args.film_scale)
        print(f"wrote {len(written)} reference(s) to {folder}")
        return 0
    if args.fit_scale is not None and not (args.calibration and args.suite == "val"):
        # Fitting on the suite the claims are measured on would make its calibration figure circular.
        print("renderloop bench: error: --fit-scale needs --calibration --suite val", file=sys.stderr)
        return 2
    if args.calibration:
        suite = "val" if args.suite == "val" else "dev"
        low, high = CEILING_RENDER_RANGE
        if args.ceiling_renders != 0 and not low <= args.ceiling_renders <= high:
            print(f"renderloop bench: error: --ceiling-renders takes {low}–{high} (or 0)", file=sys.stderr)
            return 2
        from bench.calibration_report import run_calibration_report
        report = run_calibration_report(args.out, weights_dir=args.weights, only=args.only, suite=suite,
                                        fit_scale_to=args.fit_scale, seeds=tuple(dict.fromkeys(args.seeds or (0,))),
                                        ceiling_renders=args.ceiling_renders)
        print(f"wrote {report}")
        return 0
    if args.dev_suite:
        from bench.dev_suite_report import run_dev_suite_report
        print(f"wrote {run_dev_suite_report(args.out, weights_dir=args.weights, only=args.only)}")
        return 0
    if args.loop:
        from bench.loop_report import run_loop_command
        return run_loop_command(args)
    if args.versus_mitsuba_suite:
        from bench.versus_mitsuba_suite import run_suite_summary_command
        return run_suite_summary_command(args)
    if args.versus_mitsuba:
        from bench.versus_mitsuba import run_versus_mitsuba_command
        return run_versus_mitsuba_command(args)
    if args.as_written:
        from bench.as_written import run_as_written_command
        return run_as_written_command(args)
    if args.lambda_edit:
        from bench.lambda_edit import run_lambda_edit_command
        return run_lambda_edit_command(args)
    if args.scale:
        from bench.scale_report import run_scale_report
        print(f"wrote {run_scale_report(args.out, weights_dir=args.weights)}")
        return 0
    if args.denoiser and args.suite in ("dev", "val"):
        from bench.suite_quality_report import run_suite_quality_report
        levels = {} if args.suite_spp is None else {"spp_levels": tuple(args.suite_spp)}
        report = run_suite_quality_report(args.out, weights_dir=args.weights, only=args.only, suite=args.suite,
                                          **levels)
        print(f"wrote {report}")
        return 0
    return run_measurements(args)


def run_measurements(args: argparse.Namespace) -> int:
    """--memory, --sampler (the default), --models, --denoiser: any of them, in that order."""
    if args.memory:
        from bench.sampler_report import bench_memory, write_memory_report
        memory = bench_memory()
        print(f"memory: peak RSS {memory.peak_rss_gb:.2f} GB; wrote {write_memory_report(memory, args.out)}")
    if not (args.sampler or args.models or args.denoiser or args.memory):
        args.sampler = True
    if args.sampler:
        from bench.raw_image_report import cost_rows, quality_rows, report_fields
        from bench.sampler_report import bench_sampler, write_sampler_report
        from bench.stratified_pass_report import report_fields as stratified_fields, stratified_pass_rows
        mode_started = time.perf_counter()
        results = bench_sampler(args.size or 256, args.spp or 64, args.repeats)
        for r in results:
            print(f"sampler: {r.case.label}: ours {r.ours_msps:.2f} M samples/s, mi.render {r.mi_render_msps:.2f}"
                  f" → ratio {r.ratio:.2f}x")
        quality_started = time.perf_counter()
        quality = quality_rows()
        quality_s = time.perf_counter() - quality_started
        cost = cost_rows(repeats=args.repeats)
        for q in quality:
            print(f"raw image: {q.filter} {q.spp} spp: relMSE ours / mi.render {q.ratio:.3f} ± {q.ratio_se:.3f}x "
                  f"({q.verdict}; per-pixel {q.fis_ratio:.2f}x)")
        for c in cost:
            print(f"splat cost: {c.filter} {c.spp} spp: {100 * c.overhead:+.0f} %")
        stratified = stratified_pass_rows(repeats=args.repeats)
        for s in stratified:
            print(f"stratified pass: {s.scene} {s.size}² +{s.mean_spp:.0f} spp: {s.ratio:.2f}x the independent pass")
        fields = {**report_fields(quality, cost, quality_s), **stratified_fields(stratified),
                  "mode_minutes": f"{(time.perf_counter() - mode_started) / 60:.1f}"}
        print(f"wrote {write_sampler_report(results, args.out, fields)}")
    if args.models:
        # The defaults (256² and 512², 2 threads); `python -m bench.models_report --help` has the options.
        # The shipped denoiser's architecture (models/weights/denoiser.pt, or --weights DIR's).
        from bench.models_report import main as models_main
        from models.pretrained import DENOISER_FILE, weights_dir
        shipped = weights_dir(args.weights) / DENOISER_FILE
        print(f"wrote {models_main(['--config-from', str(shipped)] if shipped.is_file() else [], out=args.out)}")
    if args.denoiser:
        if args.data is None:
            print("renderloop bench: error: --denoiser needs --data DIR with a held-out split", file=sys.stderr)
            return 2
        from bench.quality_report import run_quality_report
        weights = {} if args.weights is None else {"weights_dir": args.weights}
        print(f"wrote {run_quality_report(args.data, args.out, **weights)}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
