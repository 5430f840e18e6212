"""`renderloop bench --loop [--quick]`: what accuracy costs in wall time → docs/benchmarks.md
(+ CSV and PNGs in docs/benchmarks/).

The measuring is in `bench.loop_run`; this module runs it with the micro-benchmarks, and turns
the results into the report: tables here, prose in bench/templates/loop.md.
"""
from __future__ import annotations

import argparse
import csv
import math
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

from bench.common import (METRIC_NAMES, BenchNetworks, command_line, fill, load_average,
                          load_bench_networks, oidn_denoiser, pinned_torch_threads, provenance, scene_reference)
from bench.loop_plots import write_plots
from bench.dev_references import DEFAULT_REFERENCE_DIR, SCALED_REFERENCE_SPP, load_reference, scaled_reference_dir
from bench.loop_run import (BOUND_METHODS, DEFAULT_METHODS, DEGENERATE_PREDICTION_RATIO, DEV, FULL, LOOP_SEED, METHODS,
                            PRODUCT, QUICK, STAGES, BenchSettings, ErrorAgreement, Headline, LoopMethod, SceneResult,
                            error_agreement, headline, prepare_scenes, select_methods, warm_up)
from bench.loop_expected_bound import run_bench_method
from bench.loop_seeds import GOAL_GAP_TO_BOUND, bound_line, gaps, median_scene, seed_table
from bench.models_report import CASES as MODEL_CASES, ThreadTiming, benchmark_models, denoise_ms_by_threads
from bench.sampler_report import CASES as SAMPLER_CASES, SamplerResult, bench_sampler, sampler_table
from bench.server import bench_http_lambda
from service.render.runtime import active_variant

DEFAULT_CACHE_DIR = Path("bench-cache")  # git-ignored (/bench-cache/)
# Goals the product is measured against: time-to-SMAPE speed-ups of (d) (≥ 1.3× vs (b), what the
# error network must buy to pay for itself; ≥ 10× vs (a)). Its SMAPE at equal budget is held against
# its bound, the true-error allocation (o) (bench.loop_seeds.GOAL_GAP_TO_BOUND): a fixed (d)/(b)
# goal below what (o) itself reaches (about 0.89 on the development suite) could never be met.
GOAL_SPEEDUP_VS_A, GOAL_SPEEDUP_VS_B = 10.0, 1.3
# torch intra-op threads for every timed network call (loop, model micro-benchmarks, server):
# whichever of THREAD_PROBE_COUNTS a probe at the start of the run finds faster. OIDN's own pool
# always takes every core, so one pinned torch thread handicaps (b)–(d) against (e) wherever two
# are faster (a quiet host); on a busy one two threads can measure the neighbours instead
# (measured for the first OIDN-candidate network: 1.46× against 1.84× OIDN's time at load 5). The probe decides per run,
# and the report says what it measured.
THREAD_PROBE_COUNTS = (1, 2)
THREAD_PROBE_SIZE = 256  # the probe's image side where the suite runs at each scene's own size


@dataclass
class MicroResults:
    """Each part is None when it was not run, or the error message when it failed."""

    sampler: list[SamplerResult] | str | None = None
    models: list[dict] | str | None = None
    threads: ThreadTiming | str | None = None  # the probe that chose the run's torch threads
    http: dict | str | None = None


@dataclass
class LoopResults:
    """Everything the report states, gathered by `run_loop_benchmark`."""

    command: str
    settings: BenchSettings
    quick: bool
    nets: BenchNetworks
    oidn_status: str
    load_before: str
    threads: int  # torch intra-op threads of every timed network call (choose_torch_threads)
    scenes: list[SceneResult] = field(default_factory=list)  # the first seed's: every table but the seed spread
    head: Headline | None = None
    methods: tuple[LoopMethod, ...] = DEFAULT_METHODS
    seeds: dict[int, Headline] = field(default_factory=dict)  # every seed's headline, the first included
    seed_scenes: dict[int, list[SceneResult]] = field(default_factory=dict)  # the later seeds' runs (for the CSV)
    micro: MicroResults = field(default_factory=MicroResults)
    csv_path: Path | None = None
    plots: list[Path] = field(default_factory=list)
    seconds: float = math.nan


# --- running --------------------------------------------------------------------------------------


def run_loop_benchmark(out_dir: Path = Path("docs"), *, quick: bool = False, weights_dir: Path | None = None,
                       cache_dir: Path = DEFAULT_CACHE_DIR, command: str | None = None, suite: str = "procedural",
                       only: list[str] | None = None, film_scale: int = 1, reference_spp: int | None = None,
                       seeds: tuple[int, ...] = (LOOP_SEED,), methods: list[str] | None = None,
                       timing_repeats: int | None = None) -> Path:
    """Run the loop benchmark and write `out_dir/benchmarks.md` (+ CSV and PNGs in
    `out_dir/benchmarks/`), or `benchmarks-dev.md` for the development suite (`benchmarks-dev-xK.md`
    at film_scale K > 1, against the references `renderloop bench --references --film-scale K`
    left in the cache, of `reference_spp`; a run of only some `methods` adds their keys, e.g.
    `benchmarks-dev-bdo.md`); returns the markdown path. One loop per method, scene and
    seed: the tables are the first seed's (its stages timed `timing_repeats` times), the later seeds
    run once each for the allocation bound's spread (bench.loop_seeds)."""
    started = time.perf_counter()
    out_dir, cache_dir = Path(out_dir), Path(cache_dir)
    settings = dev_settings(film_scale, reference_spp) if suite == "dev" else QUICK if quick else FULL
    if timing_repeats is not None:
        settings = replace(settings, timing_repeats=timing_repeats)
    name = ("benchmarks-dev" + (f"-x{film_scale}" if film_scale > 1 else "")) if suite == "dev" else "benchmarks"
    chosen = select_methods(methods)
    if len(chosen) < len(DEFAULT_METHODS):  # a subset run must not overwrite the every-method report
        name += "-" + "".join(m.key for m in chosen)
    nets = load_bench_networks(weights_dir)
    probe, threads = choose_torch_threads(nets, settings.size or THREAD_PROBE_SIZE)
    with pinned_torch_threads(threads):
        results = measure_loops(settings, quick, nets, threads, cache_dir, command, only, seeds, chosen)
        if settings.micro:
            results.micro = micro_benchmarks(results.settings, results.nets, threads)
    results.micro.threads = probe
    folder = out_dir / name
    results.csv_path = write_csv({seeds[0]: results.scenes, **results.seed_scenes},
                                 folder / ("loop-quick.csv" if quick else "loop.csv"))
    results.plots = write_plots(results.scenes, results.head, folder)
    results.seconds = time.perf_counter() - started
    return write_loop_report(out_dir / f"{name}.md", results)


def dev_settings(film_scale: int = 1, reference_spp: int | None = None) -> BenchSettings:
    """The development suite's settings; at film_scale > 1 against the cached scaled references."""
    if film_scale < 1:
        raise ValueError(f"film_scale must be >= 1, got {film_scale}")
    if film_scale == 1:
        return DEV
    return replace(DEV, film_scale=film_scale, reference_spp=reference_spp or SCALED_REFERENCE_SPP)


def scene_reference_image(scene, settings: BenchSettings, cache_dir: Path):
    """A development scene's committed reference (frame 0) — or at film_scale > 1 the cached one of
    that film size and settings.reference_spp — else one rendered once and cached."""
    frame = None if scene.dev is None or scene.dev.frames == 1 else 0
    if scene.dev is not None and settings.film_scale > 1:
        folder = scaled_reference_dir(cache_dir, settings.film_scale)
        image, header = load_reference(folder, scene.dev, frame, size=scene.film)
        if header.get("spp") != settings.reference_spp:
            raise FileNotFoundError(f"{scene.label}: the cached {scene.film[0]}x{scene.film[1]} reference has "
                                    f"{header.get('spp')} spp, not {settings.reference_spp}: run `renderloop bench "
                                    f"--references --film-scale {settings.film_scale} --reference-spp "
                                    f"{settings.reference_spp} --only {scene.label}`")
        return image
    if scene.dev is not None:
        return load_reference(DEFAULT_REFERENCE_DIR, scene.dev, frame)[0]
    print(f"bench --loop: {scene.label}: reference at {settings.reference_spp} spp …", flush=True)
    return scene_reference(scene.source, scene.label, settings.size, settings.reference_spp,
                           cache_dir / "references").mean


def choose_torch_threads(nets: BenchNetworks, size: int) -> tuple[ThreadTiming | str, int]:
    """The probe's timings (or why it failed) and the thread count to run with: the faster one,
    1 when the probe failed (the count that cannot oversubscribe a busy host)."""
    try:
        probe = denoise_ms_by_threads(nets.networks.denoiser, size, THREAD_PROBE_COUNTS)
    except Exception as exc:  # the report says what failed; the run goes on
        return f"{type(exc).__name__}: {exc}", 1
    return probe, min(probe.ms_median, key=probe.ms_median.get)


def measure_loops(settings: BenchSettings, quick: bool, nets: BenchNetworks, threads: int, cache_dir: Path,
                  command: str | None, only: list[str] | None = None, seeds: tuple[int, ...] = (LOOP_SEED,),
                  methods: tuple[LoopMethod, ...] = DEFAULT_METHODS) -> LoopResults:
    if not seeds:
        raise ValueError("the loop benchmark needs at least one seed")
    oidn, oidn_status = oidn_denoiser()
    results = LoopResults(command or command_line(), settings, quick, nets, oidn_status, load_average(), threads,
                          methods=methods)
    by_seed: dict[int, list[SceneResult]] = {seed: [] for seed in seeds}
    for scene in prepare_scenes(settings, cache_dir, only):
        reference = scene_reference_image(scene, settings, cache_dir)
        warm_up(scene, settings, nets)
        for i, seed in enumerate(seeds):
            # The first seed is timed as the tables need; a later seed's images are what the spread
            # needs, and the same for any number of repeats (identical seeds, identical images).
            seeded = replace(settings, seed=seed, timing_repeats=settings.timing_repeats if i == 0 else 1)
            runs = {}
            for method in methods:
                runs[method.key] = run_bench_method(scene, method, seeded, nets, reference, oidn)
                last = runs[method.key].rows[-1]
                print(f"bench --loop: {scene.label} seed {seed} ({method.key}) SMAPE {last.metrics['smape']:.4f} "
                      f"after {last.cumulative_seconds:.2f} s", flush=True)
            by_seed[seed].append(SceneResult(scene, reference, runs))
    results.scenes = by_seed[seeds[0]]
    results.head = headline(results.scenes)
    results.seeds = {seed: headline(scenes) if seed != seeds[0] else results.head for seed, scenes in by_seed.items()}
    results.seed_scenes = {seed: scenes for seed, scenes in by_seed.items() if seed != seeds[0]}
    return results


def micro_benchmarks(settings: BenchSettings, nets: BenchNetworks, threads: int) -> MicroResults:
    """Each part is independent: one that fails is reported with its error, the rest still run."""
    size, spp, repeats = settings.sampler
    parts: dict[str, Callable[[], object]] = {
        "sampler": lambda: bench_sampler(size, spp, repeats, SAMPLER_CASES[:settings.sampler_cases]),
        "models": lambda: benchmark_models(sizes=settings.model_sizes, repeats=settings.model_repeats,
                                           threads=threads, cases=MODEL_CASES),
        "http": lambda: bench_http_lambda(settings.http_size, settings.http_requests, nets.folder, LOOP_SEED,
                                          threads),
    }
    micro = MicroResults()
    for name, run in parts.items():
        print(f"bench --loop: micro-benchmark {name} …", flush=True)
        try:
            setattr(micro, name, run())
        except Exception as exc:  # the report says what failed instead of losing the whole run
            setattr(micro, name, f"{type(exc).__name__}: {exc}")
    return micro


# --- outputs ----------------------------------------------------------------------------------------


def write_csv(by_seed: dict[int, list[SceneResult]], path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["seed", "scene", "method", "iteration", "spp_mean", *(f"{s}_s" for s in STAGES),
                         "cumulative_s", *METRIC_NAMES, "predicted_smape"])
        for seed, results in by_seed.items():
            for result in results:
                for run in result.runs.values():
                    for r in run.rows:
                        writer.writerow([seed, r.scene, r.method, r.iteration, f"{r.spp_mean:g}",
                                         *(f"{r.stage_seconds[s]:.4f}" for s in STAGES), f"{r.cumulative_seconds:.4f}",
                                         *(f"{r.metrics[m]:.6g}" for m in METRIC_NAMES),
                                         "" if r.predicted_error is None else f"{r.predicted_error:.6g}"])
    return path


def write_loop_report(path: Path, results: LoopResults) -> Path:
    s, head, scenes = results.settings, results.head, results.scenes
    rel = lambda p: p.relative_to(path.parent).as_posix()
    spps = [f"{r.spp_mean:g}" for r in scenes[0].runs[PRODUCT].rows]
    agreements = [error_agreement(result) for result in scenes]
    median_ratio = statistics.median(a.ratio for a in agreements) if agreements else math.nan
    plots = results.plots
    path.write_text(fill(
        "loop.md",
        provenance=provenance(results.command, active_variant()),
        load_before=results.load_before, load_after=load_average(), minutes=f"{results.seconds / 60:.1f}",
        weights=results.nets.description,
        quick=" (**--quick**: small images, few scenes and iterations; not the real report)" if results.quick else "",
        size_label=size_label(s),
        suite=suite_note(s), iterations=s.iterations, spps=", ".join(spps), last_spp=spps[-1], reference_spp=s.reference_spp,
        repeats=s.timing_repeats, threads=results.threads,
        methods="; ".join(f"({m.key}) {m.label}" for m in results.methods), oidn_status=results.oidn_status,
        bound=bound_line(results.seeds), seed_note=seed_note(results), seed_table=seed_table(results.seeds),
        headline_table=headline_table(scenes, head), goals="; ".join(goal_lines(head)),
        error_plot=f"![SMAPE vs cumulative wall time, log-log, one panel per scene; dotted: the target]({rel(plots[0])})"
        if plots else "(no plots: matplotlib is not installed)",
        last_table=last_iteration_table(scenes), csv_link=f"[{results.csv_path.name}]({rel(results.csv_path)})",
        per_iteration=per_iteration_tables(scenes), agreement="\n".join(agreement_line(a) for a in agreements),
        degenerate=degenerate_note(median_ratio),
        other_plots="\n\n".join(f"![{p.stem.replace('_', ' ')}]({rel(p)})" for p in plots[1:]),
        micro=micro_sections(results.micro, s) if s.micro else "Not part of this run (see docs/benchmarks.md).",
        threads_note=threads_note(results.micro.threads),
    ))
    return path


def seed_note(results: LoopResults) -> str:
    """Which methods and seeds this run measured, for the bound's section."""
    seeds = list(results.seeds)
    keys = ", ".join(f"({m.key})" for m in results.methods)
    everything = "every method" if results.methods == DEFAULT_METHODS else (
        f"only {keys} (`--methods`: what the bound needs is {', '.join(f'({k})' for k in BOUND_METHODS)})")
    if len(seeds) == 1:
        return (f"One loop seed ({seeds[0]}) and {everything}: `--seeds 0 1 2` gives the spread over seeds (the s.d. "
                "needs two).")
    return (f"Loop seeds {', '.join(map(str, seeds))} (`--seeds`), {everything}, {size_label(results.settings)}, "
            f"{results.settings.iterations} iterations. Every table above is seed {seeds[0]}'s; the later seeds ran "
            "each loop once (their images, not their times, are what this table needs). Each cell: mean ± sample "
            "standard deviation over the seeds (min–max in brackets); the median row takes, per seed, the median "
            "over the scenes, then its spread over the seeds.")


def size_label(settings: BenchSettings) -> str:
    if settings.size:
        return f"{settings.size}×{settings.size}"
    if settings.film_scale > 1:
        side = 256 * settings.film_scale
        return f"{settings.film_scale}× each scene's film size in width and height (about {side}²)"
    return "each scene's own film size (about 256²)"


def suite_note(settings: BenchSettings) -> str:
    if settings.suite == "dev" and settings.film_scale > 1:
        return (f"Scenes: the hand-written development scenes (scenes/dev, never trained on), rendered as written "
                f"but for the film's size, against references at that size (mi.render of the same resized scene, "
                f"{settings.reference_spp} spp, made by `renderloop bench --references --film-scale "
                f"{settings.film_scale}` and cached in the bench cache, not committed; not rendered by this run). "
                "At this spp a reference's own noise is a visible part of the smallest errors below, the same "
                "for every method: it pulls ratios between methods towards 1.")
    if settings.suite == "dev":
        return ("Scenes: the twelve hand-written development scenes (scenes/dev, never trained on), rendered as "
                "written, against their committed references (scenes/dev/references: mi.render as written, "
                "16 384 spp, 65 536 for the three noisiest; not rendered by this run).")
    return ("Scenes: built-ins and held-out procedural scenes, each reference rendered once by the same "
            "renderer and integrator with its own seed and cached on disk (`--cache`, default `bench-cache/`).")


def fmt_time(seconds: float, how: str) -> str:
    if not math.isfinite(seconds):
        return "never"
    mark = {"interpolated": "", "first iteration": "≤", "extrapolated": "~"}.get(how, "")
    return f"{mark}{seconds:.2f}"


def fmt_ratio(value: float) -> str:
    return f"{value:.2f}×" if math.isfinite(value) else "∞"


def headline_table(scenes: list[SceneResult], head: Headline) -> str:
    methods = [m for m in METHODS if any(m.key in r.runs for r in scenes)]
    others = [m for m in methods if m.key != PRODUCT]
    lines = ["| scene | target SMAPE | " + " | ".join(f"({m.key}) s" for m in methods) + " | "
             + " | ".join(f"(d) vs ({m.key})" for m in others) + " | SMAPE (d)/(b) | SMAPE (o)/(b) |",
             "|---|---:|" + "---:|" * len(methods) + "---:|" * len(others) + "---:|---:|"]
    for result in scenes:
        label = result.scene.label
        lines.append(f"| {label} | {head.target[label]:.4f} | "
                     + " | ".join(fmt_time(*head.times[label][m.key]) for m in methods) + " | "
                     + " | ".join(fmt_ratio(head.speedup[label][m.key]) for m in others)
                     + f" | {head.smape_ratio.get(label, math.nan):.2f} | {head.oracle_ratio.get(label, math.nan):.2f} |")
    lines.append("| **median** | | " + " | ".join("" for _ in methods) + " | "
                 + " | ".join(f"**{fmt_ratio(head.median_speedup[m.key])}**" for m in others)
                 + f" | **{head.median_smape_ratio:.2f}** | **{head.median_oracle_ratio:.2f}** |")
    return "\n".join(lines)


def goal_lines(head: Headline) -> list[str]:
    out = []
    for key, goal in (("a", GOAL_SPEEDUP_VS_A), ("b", GOAL_SPEEDUP_VS_B)):
        if key in head.median_speedup:
            value = head.median_speedup[key]
            out.append(f"median speed-up vs ({key}) {fmt_ratio(value)} (goal ≥ {goal:g}×: "
                       f"{'met' if value >= goal else 'not met'})")
    if math.isfinite(head.median_smape_ratio):
        out.append(f"median SMAPE (d)/(b) {head.median_smape_ratio:.2f} at equal samples")
    if math.isfinite(head.median_oracle_ratio):
        gap = statistics.median(gaps(head).values())
        out.append(f"with a perfect error map (o) the same allocation would reach a median SMAPE (o)/(b) "
                   f"{head.median_oracle_ratio:.2f}: the most error-driven allocation gains on these scenes; "
                   f"median gap (d)/(b) − (o)/(b) {gap:.3f} (goal ≤ {GOAL_GAP_TO_BOUND}: "
                   f"{'met' if gap <= GOAL_GAP_TO_BOUND else 'not met'}; over seeds in \"Against the bound\")")
    versus_oidn = [speedups["e"] for speedups in head.speedup.values() if "e" in speedups]
    if versus_oidn:
        # (e) needing longer than (d) to reach (d)'s final SMAPE = (d) is ahead at equal wall time.
        out.append(f"(d) ahead of (e) uniform + OIDN at equal wall time on {sum(v > 1 for v in versus_oidn)} of "
                   f"{len(versus_oidn)} scenes")
    return out


def last_iteration_table(scenes: list[SceneResult]) -> str:
    lines = ["| scene | method | spp | total s | render | denoise | error | allocate | SMAPE | relMSE | PSNR dB | DSSIM |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for result in scenes:
        for key, run in result.runs.items():
            last = run.rows[-1]
            totals = {st: sum(r.stage_seconds[st] for r in run.rows) for st in STAGES}
            m = last.metrics
            lines.append(f"| {result.scene.label} | ({key}) | {last.spp_mean:g} | {last.cumulative_seconds:.2f} | "
                         + " | ".join(f"{totals[st]:.2f}" for st in STAGES)
                         + f" | {m['smape']:.4f} | {m['relmse']:.4g} | {m['psnr']:.2f} | {m['dssim']:.4f} |")
    return "\n".join(lines)


def per_iteration_tables(scenes: list[SceneResult]) -> str:
    blocks = []
    for result in scenes:
        lines = [f"**{result.scene.label}** ({result.scene.origin})", "",
                 "| spp | " + " | ".join(f"({k})" for k in result.runs) + " |", "|---:|" + "---|" * len(result.runs)]
        for i, row in enumerate(result.runs[PRODUCT].rows):
            cells = [f"{run.rows[i].metrics['smape']:.4f} @ {run.rows[i].cumulative_seconds:.2f} s"
                     for run in result.runs.values()]
            lines.append(f"| {row.spp_mean:g} | " + " | ".join(cells) + " |")
        blocks.append("\n".join(lines))
    return "\n\n".join(blocks)


def agreement_line(a: ErrorAgreement) -> str:
    return (f"- {a.scene}: (d) spp per pixel min {a.spp_min} / median {a.spp_median:g} / max {a.spp_max}; "
            f"predicted vs true per-pixel SMAPE (last iteration): r = {a.correlation:.2f}, mean predicted / true "
            f"= {a.ratio:.3g}"  # (a)'s convergence only when the run had (a) (else its exponent is NaN)
            + ("" if math.isnan(a.exponent) else f"; (a) converges as SMAPE ∝ spp^{a.exponent:.2f}") + ".")


def degenerate_note(median_ratio: float) -> str:
    if not median_ratio < DEGENERATE_PREDICTION_RATIO:
        return ""
    return (f"**The error network's prediction is degenerate** (median mean predicted / true SMAPE "
            f"{median_ratio:.3g}): it predicts almost no error anywhere, so (d) hands samples out by numerical "
            "dust (or uniformly, where the map is exactly 0) and behaves like (b). The (d) columns of the "
            "headline therefore say nothing about error-driven sampling with these weights.")


def micro_sections(micro: MicroResults, settings: BenchSettings) -> str:
    parts = ["### Renderer throughput vs `mi.render` (equal samples)", ""]
    if isinstance(micro.sampler, str):
        parts.append(f"Failed: {micro.sampler}")
    elif micro.sampler:
        first = micro.sampler[0]
        parts += [f"{first.size}², {first.spp} spp, median of {len(first.ratios)} interleaved runs "
                  "(`bench.sampler_report`; ours also computes albedo/normal/depth and per-pixel sums).", "",
                  sampler_table(micro.sampler)]
    parts += ["", "### Denoiser speed and memory (`bench.models_report`, CPU)", ""]
    if isinstance(micro.models, str):
        parts.append(f"Failed: {micro.models}")
    elif micro.models:
        parts += ["Default `DenoiserConfig` (same cost as trained weights of that configuration), fresh process "
                  "per case, median of the timed runs after a warm-up; `lambda-tail` / `lambda-tail-map` are the "
                  "λ-only re-run from cached temporal features with a global λ / a per-pixel λ map (what a λ "
                  "edit costs).", "",
                  "| case | size | threads | median ms | min ms | ms / megapixel | peak RSS MB | RSS growth MB |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|"]
        for r in micro.models:
            megapixels = r["size"] ** 2 / 1e6
            parts.append(f"| {r['model']} | {r['size']}² | {r['threads']} | {r['ms_median']:.1f} | {r['ms_min']:.1f} | "
                         f"{r['ms_median'] / megapixels:.0f} | {r['peak_rss_mb']:.0f} | {r['peak_rss_growth_mb']:.0f} |")
        tails = [r for r in micro.models if r["model"].startswith("lambda-tail")]
        if tails:
            parts += ["", "λ tail latency: " + "; ".join(
                f"{r['model']} {r['size']}²: median {r['ms_median']:.1f} ms (min {r['ms_min']:.1f})" for r in tails) + "."]
    parts += ["", "### λ over HTTP (real uvicorn server, `PUT /jobs/{id}/lambda` on a finished job)", ""]
    http = micro.http
    if isinstance(http, str):
        parts.append(f"Failed: {http}")
    elif http:
        parts.append(f"{http['size']}² Cornell box, {http['requests']} requests after one warm-up, alternating a "
                     f"global λ and a painted rectangle: **p50 {http['p50_ms']:.1f} ms, p95 {http['p95_ms']:.1f} ms** "
                     f"(max {http['max_ms']:.1f} ms); {http['tail_passes']} λ-tail passes, {http['full_passes']} full "
                     "denoiser passes.")
    return "\n".join(parts)


def threads_note(timing: ThreadTiming | str | None) -> str:
    if isinstance(timing, ThreadTiming):
        measured = " and ".join(f"{ms:.1f} ms with {t} thread{'s' if t > 1 else ''}"
                                for t, ms in timing.ms_median.items())
        return (f"Measured at the start of this run, in this process, with the loaded denoiser: one "
                f"single-frame {timing.size}² denoise took {measured} (median of {timing.repeats}, "
                "interleaved); the faster count ran everything.")
    return f"The one-vs-two-thread probe failed ({timing}), so everything ran on one thread." if timing \
        else "The thread probe was not run."


# --- the command ------------------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The `renderloop bench` flags this module owns."""
    parser.add_argument("--loop", action="store_true",
                        help="render loop benchmark: error vs wall time per method → docs/benchmarks.md")
    parser.add_argument("--quick", action="store_true", help="with --loop: small images, two scenes, three iterations")
    parser.add_argument("--weights", type=Path, default=None,
                        help="with --loop or --denoiser: weights folder (default models/weights)")
    parser.add_argument("--cache", type=Path, default=DEFAULT_CACHE_DIR, help="with --loop: reference cache folder")
    parser.add_argument("--film-scale", type=int, default=1, metavar="K",
                        help="with --loop --suite dev or --references: each film's width and height × K (2: about "
                             "512²), against references rendered by --references --film-scale K into the cache")
    parser.add_argument("--timing-repeats", type=int, default=None, metavar="K",
                        help="with --loop: identical runs of each loop whose fastest stages count (default 3, "
                             "2 with --suite dev, 1 with --quick; later --seeds always run once)")
    parser.add_argument("--methods", nargs="+", default=None, metavar="KEY",
                        help=f"with --loop: only these methods ({', '.join(m.key for m in METHODS)}; must include {PRODUCT}; "
                             f"x, four loops each, only when named); the bound needs {' '.join(BOUND_METHODS)}")
    parser.add_argument("--suite", choices=("procedural", "dev", "val"), default="procedural",
                        help="with --loop: 'dev' runs the development suite at its own sizes → benchmarks-dev.md; "
                             "with --denoiser or --references: 'dev' (scenes/dev) or 'val' (scenes/val, "
                             "the validation scenes networks are chosen on)")


def run_loop_command(args: argparse.Namespace) -> int:
    if args.suite == "val":
        print("renderloop bench: error: --loop runs on --suite procedural or dev; the validation scenes "
              "(--suite val) are for --denoiser", file=sys.stderr)
        return 2
    if args.film_scale != 1 and args.suite != "dev":
        print("renderloop bench: error: --film-scale runs the development suite: add --suite dev", file=sys.stderr)
        return 2
    try:
        select_methods(args.methods)
    except ValueError as exc:
        print(f"renderloop bench: error: --methods: {exc}", file=sys.stderr)
        return 2
    if args.timing_repeats is not None and args.timing_repeats < 1:
        print("renderloop bench: error: --timing-repeats must be >= 1", file=sys.stderr)
        return 2
    try:  # a missing scaled reference is answered before the networks load and the ~17 s thread probe
        scaled = dev_settings(args.film_scale, args.reference_spp) if args.film_scale > 1 else None
        for scene in prepare_scenes(scaled, args.cache, args.only) if scaled else ():
            scene_reference_image(scene, scaled, args.cache)
        path = run_loop_benchmark(args.out, quick=args.quick, weights_dir=args.weights, cache_dir=args.cache,
                                  suite=args.suite, only=args.only, film_scale=args.film_scale,
                                  reference_spp=args.reference_spp, seeds=tuple(dict.fromkeys(args.seeds or (LOOP_SEED,))),
                                  methods=args.methods, timing_repeats=args.timing_repeats)
    except FileNotFoundError as exc:  # a scaled reference not rendered yet: the message names the command
        print(f"renderloop bench: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {path}")
    return 0
