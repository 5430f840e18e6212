"""`renderloop bench --versus-mitsuba`: the loop against `mi.render` + OIDN where users render
(each scene as written, its film scaled to ~2 MP) → docs/benchmarks-versus-mitsuba.md with `-o docs`.

The measuring is in bench.versus_mitsuba_run (curves), bench.versus_mitsuba_scene (scenes,
references) and bench.versus_mitsuba_costs (fixed costs per iteration); this module runs them per
scene and writes the report: tables here, prose in bench/templates/versus_mitsuba.md.
"""
from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

from bench.common import BenchNetworks, OidnDenoise, command_line, load_average, load_bench_networks, oidn_denoiser, pinned_torch_threads
from bench.dev_references import DEV_SCENES, VAL_SCENES, DevScene, dev_scenes
from bench.loop_report import DEFAULT_CACHE_DIR, THREAD_PROBE_SIZE, choose_torch_threads
from bench.versus_mitsuba_costs import measure_fixed_costs
from bench.versus_mitsuba_report import LOOP, LOOP_LABEL, UNIFORM, CostProbe, Results, SceneRun, Settings, report_text
from bench.versus_mitsuba_run import Curve, better_of, compare, loop_curve, mitsuba_curve, spp_levels, warm_up_loop
from bench.versus_mitsuba_scene import reference, scaled_film, scene_filter
from service.render.runtime import network_device

REPORT_NAME = "benchmarks-versus-mitsuba.md"
GPU_REPORT_NAME = "benchmarks-versus-mitsuba-gpu.md"  # networks and OIDN on CUDA: a report of its own
DEFAULT_MEGAPIXELS, DEFAULT_MAX_SPP, DEFAULT_REFERENCE_SPP = 2.0, 1024, 4096
SUITE_ROOTS = (DEV_SCENES, VAL_SCENES)


def suite_scenes(names: list[str] | None) -> list[DevScene]:
    """The scenes of scenes/dev and scenes/val (in that order), or those named (in the order named:
    a run cut short has measured the first ones)."""
    found = [scene for root in SUITE_ROOTS for scene in dev_scenes(None, root)]
    if not names:
        return found
    unknown = sorted(set(names) - {s.name for s in found})
    if unknown:
        raise ValueError(f"unknown scene(s) {', '.join(unknown)}; known: {', '.join(s.name for s in found)}")
    by_name = {s.name: s for s in found}
    return [by_name[name] for name in dict.fromkeys(names)]


def run_scene(scene: DevScene, settings: Settings, nets: BenchNetworks, oidn: OidnDenoise) -> SceneRun:
    film = scaled_film(scene, settings.megapixels)
    levels = spp_levels(settings.max_spp)
    rfilter = scene_filter(scene)
    say = lambda text: print(f"bench --versus-mitsuba: {scene.name} ({film}): {text}", flush=True)
    say(f"reference at {settings.reference_spp} spp …")
    ref = reference(scene, film, settings.reference_spp, settings.cache_dir)
    curves: dict[str, Curve] = {}
    for box in ((False,) if rfilter == "box" else (False, True)):
        curve = mitsuba_curve(scene, film, box, levels, ref, oidn)
        curves[curve.key] = curve
        say(f"{curve.label}: SMAPE {curve.points[-1].smape:.4f} at {levels[-1]} spp, {curve.points[-1].seconds:.1f} s")
    warm_up_loop(scene, film, nets.networks)
    loop = loop_curve(LOOP, LOOP_LABEL, scene, film, nets.networks, "error", levels, ref)
    uniform = loop_curve(UNIFORM, "uniform + ours", scene, film, nets.networks, "uniform", levels, ref)
    curves[LOOP], curves[UNIFORM] = loop.curve, uniform.curve
    say(f"loop: SMAPE {loop.curve.points[-1].smape:.4f} after {loop.curve.points[-1].seconds:.1f} s")
    competitors = [c for k, c in curves.items() if k.startswith("mitsuba")]
    versus = better_of(loop.curve, competitors)
    costs = measure_fixed_costs(scene.name, loop)
    return SceneRun(scene, film, rfilter, ref.relative_error, curves, versus, compare(loop.curve, uniform.curve), costs,
                    better_of(loop.curve, competitors, "relmse"))


def probe_costs(scene: DevScene, megapixels: float, nets: BenchNetworks) -> CostProbe:
    """Fixed costs and memory of one 16-spp loop iteration at `megapixels` (no reference needed)."""
    film = scaled_film(scene, megapixels)
    print(f"bench --versus-mitsuba: {scene.name} ({film}): fixed costs of one iteration …", flush=True)
    warm_up_loop(scene, film, nets.networks)
    run = loop_curve(LOOP, LOOP_LABEL, scene, film, nets.networks, "error", [16], None)
    return CostProbe(scene.name, film, measure_fixed_costs(scene.name, run), run.curve.peak_rss_mb,
                     run.curve.rss_growth_mb)


def measure_versus_mitsuba(*, megapixels: float = DEFAULT_MEGAPIXELS, max_spp: int = DEFAULT_MAX_SPP,
                           reference_spp: int = DEFAULT_REFERENCE_SPP, scenes: list[str] | None = None,
                           weights_dir: Path | None = None, cache_dir: Path = DEFAULT_CACHE_DIR,
                           threads: int | None = None, command: str | None = None,
                           costs_megapixels: float | None = None,
                           after_scene: Callable[[Results], object] | None = None) -> Results:
    """Measure every scene (or those named). `threads`: torch intra-op threads (None: probe 1 vs 2
    and take the faster, as `renderloop bench --loop` does). `costs_megapixels`: also the fixed
    costs of one iteration on the first scene at that size (the fixed costs at ~2 MP from a small run).
    `after_scene`: called with the results so far after each scene (the command writes the report
    then, so a run cut short keeps every finished scene)."""
    started = time.perf_counter()
    spp_levels(max_spp)  # refuses a max below the first iteration before anything runs
    chosen = suite_scenes(scenes)
    nets = load_bench_networks(weights_dir)
    if threads is None:  # on a GPU the networks run there: torch's host threads as it sets them
        threads = (torch.get_num_threads() if network_device() == "cuda" else
                   choose_torch_threads(nets, THREAD_PROBE_SIZE)[1])
    settings = Settings(megapixels, max_spp, reference_spp, threads, command or command_line(), Path(cache_dir),
                        tuple(scenes or ()))
    oidn, oidn_status = oidn_denoiser()
    results = Results(settings, nets, oidn_status, load_average())
    with pinned_torch_threads(threads):
        for scene in chosen:
            results.scenes.append(run_scene(scene, settings, nets, oidn))
            results.seconds = time.perf_counter() - started
            if after_scene is not None:
                after_scene(results)
        if costs_megapixels is not None:
            results.probe = probe_costs(chosen[0], costs_megapixels, nets)
    results.seconds = time.perf_counter() - started
    return results


def report_name() -> str:
    """The CPU and the GPU reports side by side in docs/: a run on a GPU never overwrites the CPU's."""
    return GPU_REPORT_NAME if network_device() == "cuda" else REPORT_NAME


def write_report(results: Results, out_dir: Path) -> Path:
    out = Path(out_dir) / report_name()
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(report_text(results))
    return out


def run_versus_mitsuba(out_dir: Path = Path("docs"), **options) -> Path:
    """Measure (measure_versus_mitsuba's options) and write `out_dir`/report_name(), after each
    scene and at the end."""
    return write_report(measure_versus_mitsuba(after_scene=lambda so_far: write_report(so_far, out_dir), **options),
                        out_dir)


# --- the command ------------------------------------------------------------------------------------


def scene_list(text: str) -> list[str]:
    names = [name.strip() for name in text.split(",") if name.strip()]
    if not names:
        raise argparse.ArgumentTypeError("give scene names separated by commas, e.g. metals,hard_shadows")
    return names


def positive_megapixels(text: str) -> float:
    value = float(text)
    if not 0 < value <= 16:
        raise argparse.ArgumentTypeError(f"--megapixels must be in (0, 16], got {text}")
    return value


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The `renderloop bench` flags this module owns (--weights, --cache, --reference-spp, -o are shared)."""
    parser.add_argument("--versus-mitsuba", action="store_true",
                        help="the loop vs mi.render + OIDN (scene's filter and box) on scenes/dev and scenes/val as "
                             f"written, films scaled to --megapixels → {REPORT_NAME} ({GPU_REPORT_NAME} with "
                             "the networks on CUDA)")
    parser.add_argument("--versus-mitsuba-suite", action="store_true",
                        help="the suite's standing over every --versus-mitsuba report in -o (each scene's newest "
                             "reading, the bars counted against all of scenes/dev and scenes/val) → "
                             "benchmarks-versus-mitsuba-suite.md there")
    parser.add_argument("--megapixels", type=positive_megapixels, default=DEFAULT_MEGAPIXELS,
                        help=f"with --versus-mitsuba: each film scaled to about this many MP, aspect kept "
                             f"(default {DEFAULT_MEGAPIXELS:g}, about 1080p)")
    parser.add_argument("--max-spp", type=int, default=DEFAULT_MAX_SPP,
                        help=f"with --versus-mitsuba: uniform spp 16, 32, … up to this (default {DEFAULT_MAX_SPP})")
    parser.add_argument("--costs-megapixels", type=positive_megapixels, default=None, metavar="MP",
                        help="with --versus-mitsuba: also measure one loop iteration's fixed costs and memory at "
                             "this size on the first scene (no reference needed; e.g. 2 from a small run)")
    parser.add_argument("--scenes", type=scene_list, default=None, metavar="A,B",
                        help="with --versus-mitsuba: these scenes of scenes/dev or scenes/val only")


def run_versus_mitsuba_command(args: argparse.Namespace) -> int:
    try:  # an unknown scene, a --max-spp below 16: said before anything runs
        suite_scenes(args.scenes)
        spp_levels(args.max_spp)
    except ValueError as exc:
        print(f"renderloop bench: error: {exc}", file=sys.stderr)
        return 2
    path = run_versus_mitsuba(args.out, megapixels=args.megapixels, max_spp=args.max_spp,
                              reference_spp=args.reference_spp or DEFAULT_REFERENCE_SPP, scenes=args.scenes,
                              weights_dir=args.weights, cache_dir=args.cache, costs_megapixels=args.costs_megapixels)
    print(f"wrote {path}")
    return 0
