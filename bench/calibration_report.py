"""`renderloop bench --calibration`: can a user trust the predicted error? On the hand-written
development scenes (never trained on) and their committed references, or with `--suite val` on
the validation scenes (where error networks are compared before one ships).

Per scene, one adaptive loop (error allocator, 16 → 256 spp mean) at the scene's own size; per
iteration the mean predicted SMAPE of the denoised image next to its true SMAPE against the
reference, and the per-image Spearman rank correlation of the predicted and true error maps.
A loop with `--target-error E` stops at the first iteration whose mean prediction is ≤ E, and
the loop is deterministic for a seed, so the same records say where each E would stop and how
far the true SMAPE is from E there.
"""
from __future__ import annotations

import math
import statistics
from dataclasses import dataclass
from pathlib import Path

from bench.calibration_ceiling import CEILING_RENDERS, CeilingScore, FirstIterationMaps, ceiling_bound_line, ceiling_table, scene_ceiling
from bench.common import fill, fmt, image_metrics, load_bench_networks, pinned_torch_threads, provenance, true_error_map
from bench.dev_references import SUITES, dev_scenes, load_reference
from bench.quality_measures import block_means, spearman
from models.checkpoint import load_checkpoint, save_checkpoint
from models.pretrained import ERROR_PREDICTOR_FILE
from service.loop.change_calibration import calibrated_mean, image_change
from service.loop.loop import RenderLoop
from service.loop.spec import LoopSpec
from service.render.runtime import active_variant

REPORT_NAMES = {"dev": "calibration.md", "val": "calibration-val.md"}  # --suite → the report's file
ITERATIONS = 5  # 16 → 32 → 64 → 128 → 256 spp mean
TARGETS = (0.01, 0.02, 0.05)
TRUSTED = 0.25  # a target-error stop is trusted when its true SMAPE is within 25 % of the target
MEAN_TOLERANCE = 0.20  # the goal: predicted mean within 20 % of the true mean
UNREACHED_TARGET = 1e-9  # a --target-error no scene's prediction reaches within ITERATIONS
TORCH_THREADS = 1


# The allocator dilates and clamps the map, so what it acts on is the error of neighbourhoods;
# a single pixel's true SMAPE is mostly that pixel's leftover noise, which no network can predict.
RANKING_BLOCK = 8


@dataclass(frozen=True)
class IterationScore:
    spp: float
    predicted: float  # the loop's mean: what --target-error stops on
    true: float
    spearman: float  # per pixel: what the allocator ranks by (goal ≥ 0.7)
    block_spearman: float = float("nan")  # of RANKING_BLOCK² tile means
    network: float = float("nan")  # the error network's own mean, before the change calibration
    change: float = float("nan")    # mean SMAPE between this iteration's denoised image and the last one's

    @property
    def ratio(self) -> float:
        return self.predicted / self.true if self.true > 0 else float("nan")

    @property
    def network_ratio(self) -> float:
        return self.network / self.true if self.true > 0 else float("nan")


def calibration_spec(path: Path, iterations: int = ITERATIONS, seed: int = 0) -> LoopSpec:
    # Run as a job that stops on a target error runs (its first iteration in two halves, so that
    # mean is calibrated too: RenderLoop._splits_first_iteration), with a target no scene reaches:
    # until it stops, a loop with any target E does exactly this, so these records say where E stops.
    return LoopSpec(scene=str(path), max_iterations=iterations, allocator="error", target_error=UNREACHED_TARGET,
                    seed=seed)


def score_scene(path: Path, reference, networks, seed: int = 0) -> list[IterationScore]:
    scores, previous = [], None
    for record in RenderLoop(calibration_spec(path, seed=seed), networks).run():
        denoised, predicted = record.denoised[0], record.error[0]
        true = true_error_map(denoised, reference)
        scores.append(IterationScore(record.spp_mean, float(predicted.mean()),
                                     image_metrics(denoised, reference)["smape"], spearman(predicted, true),
                                     spearman(block_means(predicted, RANKING_BLOCK), block_means(true, RANKING_BLOCK)),
                                     network=record.network_error,
                                     change=float("nan") if previous is None else image_change(previous, denoised)))
        previous = denoised
    return scores


def first_iteration_maps(path: Path, reference, networks, seed: int) -> tuple[float, FirstIterationMaps]:
    """(spp, true and predicted maps) of the report's first iteration with `seed`: the same loop as
    score_scene's, stopped there, so the ceiling is measured on what the report's Spearman scores."""
    record = next(iter(RenderLoop(calibration_spec(path, iterations=1, seed=seed), networks).run()))
    return record.spp_mean, FirstIterationMaps(true_error_map(record.denoised[0], reference), record.error[0])


def stop_for_target(scores: list[IterationScore], target: float) -> IterationScore | None:
    """Where `--target-error target` would stop: the first iteration predicted at or below it."""
    return next((s for s in scores if s.predicted <= target), None)


def fitted_output_scale(results: dict[str, list[IterationScore]]) -> float:
    """The factor that makes the median ÷ true ratio of the network's own mean over every (scene,
    iteration) 1. A median of ratios (not a ratio of sums) so one scene with a large error does not set it."""
    ratios = [s.network_ratio for scores in results.values() for s in scores
              if math.isfinite(s.network_ratio) and s.network_ratio > 0]
    if not ratios:
        raise ValueError("no iteration with a positive true and predicted error to fit a scale on")
    return 1.0 / statistics.median(ratios)


def fitted_change_scale(results: dict[str, list[IterationScore]], output_scale: float) -> float:
    """s such that √(P·s·C) (service.loop.change_calibration) has a median ÷ true ratio of 1 over
    every iteration with a previous one, P being the network's mean after `output_scale`."""
    ratios = [s.true / calibrated_mean(s.network * output_scale, s.change, 1.0) for scores in results.values()
              for s in scores if math.isfinite(s.change) and s.change > 0 and s.network > 0 and s.true > 0]
    if not ratios:
        raise ValueError("no iteration with a change, a prediction and a true error to fit a change scale on")
    return statistics.median(ratios) ** 2


def write_calibrated_error_network(source_dir: Path, target_dir: Path, scale: float, command: str,
                                   change_scale: float | None = None) -> Path:
    """Copy source_dir's error network to target_dir with its output scale multiplied by `scale`
    and its change scale set (None: left as it was), recording `command` in the checkpoint (the
    shipped weights say how they were made)."""
    model = load_checkpoint(source_dir / ERROR_PREDICTOR_FILE, "error_predictor")
    model.config.output_scale *= scale
    if change_scale is not None:
        model.config.change_scale = change_scale
    extra = dict(model.checkpoint_extra)
    change = "" if model.config.change_scale is None else f", change_scale {model.config.change_scale:.4f}"
    extra["calibration"] = f"output_scale {model.config.output_scale:.4f}{change} by {command}"
    return save_checkpoint(target_dir / ERROR_PREDICTOR_FILE, model, extra)


def run_calibration_report(out_dir: Path, *, weights_dir: Path | None = None, only: list[str] | None = None,
                           suite: str = "dev", fit_scale_to: Path | None = None, seeds: tuple[int, ...] = (0,),
                           ceiling_renders: int = CEILING_RENDERS) -> Path:
    """Measure and write the report; with `fit_scale_to`, also write the calibrated error network there.
    One loop per scene and seed (the tables are the first seed's, the spread is over all); with
    `ceiling_renders` K > 0, K more first iterations per scene for the repeatable ceiling."""
    if not seeds:
        raise ValueError("the calibration report needs at least one seed")
    nets = load_bench_networks(weights_dir)
    by_seed: dict[int, dict[str, list[IterationScore]]] = {seed: {} for seed in seeds}
    ceiling: dict[str, CeilingScore] = {}
    with pinned_torch_threads(TORCH_THREADS):
        for scene in dev_scenes(only, SUITES[suite].root):
            reference, _ = load_reference(SUITES[suite].references, scene, None if scene.frames == 1 else 0)
            for seed in seeds:
                by_seed[seed][scene.name] = score_scene(scene.path, reference, nets.networks, seed)
                last = by_seed[seed][scene.name][-1]
                print(f"bench --calibration: {scene.name} seed {seed}: predicted {last.predicted:.4f} "
                      f"true {last.true:.4f} spearman {last.spearman:.2f}", flush=True)
            if ceiling_renders:
                ceiling[scene.name] = scene_ceiling(
                    lambda seed: first_iteration_maps(scene.path, reference, nets.networks, seed), ceiling_renders)
                print(f"bench --calibration: {scene.name}: ceiling {ceiling[scene.name].ceiling:.2f} "
                      f"network {ceiling[scene.name].network:.2f}", flush=True)
    results = by_seed[seeds[0]]
    if fit_scale_to is not None:
        scale = fitted_output_scale(results)
        change_scale = fitted_change_scale(results, scale)
        command = (f"renderloop bench --calibration --suite {suite} --weights {nets.folder} --fit-scale {fit_scale_to}"
                   + (f" --only {' '.join(only)}" if only else ""))
        written = write_calibrated_error_network(nets.folder, fit_scale_to, scale, command, change_scale)
        print(f"bench --calibration: output scale ×{scale:.4f}, change scale {change_scale:.4f} → {written}", flush=True)
    return write_calibration_report(results, out_dir, nets.description, suite, by_seed=by_seed, ceiling=ceiling)


def _per_iteration_table(results: dict[str, list[IterationScore]]) -> str:
    rows = []
    for name, scores in results.items():
        cells = " | ".join(f"{fmt(s.predicted)} / {fmt(s.true)} ({s.spearman:.2f})" for s in scores)
        rows.append(f"| {name} | {cells} |")
    return "\n".join(rows)


@dataclass(frozen=True)
class StopCounts:
    """Where --target-error E stops, counted over the scenes."""

    stops: int      # scenes whose prediction reaches E within the run
    trusted: int    # of them, true SMAPE within TRUSTED of E at the stop
    first: int      # of them, stopped after the first iteration (16 spp): no sampling choice was made
    first_below: int  # of those, true SMAPE below (1 − TRUSTED)·E: the first pass already beat E by more


def stop_counts(results: dict[str, list[IterationScore]], target: float) -> StopCounts:
    stops = [(scores, stop) for scores in results.values() if (stop := stop_for_target(scores, target)) is not None]
    trusted = [abs(stop.true / target - 1) <= TRUSTED for _, stop in stops]
    first = [stop is scores[0] for scores, stop in stops]
    below = [f and stop.true / target < 1 - TRUSTED for f, (_, stop) in zip(first, stops)]
    return StopCounts(len(stops), sum(trusted), sum(first), sum(below))


def _target_table(results: dict[str, list[IterationScore]]) -> str:
    rows = []
    final_spp = f"{max(scores[-1].spp for scores in results.values()):g}"
    for target in TARGETS:
        stops = [(name, s) for name, scores in results.items() if (s := stop_for_target(scores, target)) is not None]
        counts = stop_counts(results, target)
        cells = ", ".join(f"{name} {s.spp:g} spp → {s.true / target:.2f}×" for name, s in stops) or "—"
        never = len(results) - counts.stops
        rows.append(f"| {target:g} | {counts.stops} ({never} never reach it by {final_spp} spp) | {counts.trusted} | "
                    f"{counts.first} ({counts.first_below}) | {cells} |")
    return "\n".join(rows)


# The seed-spread table's columns: (header, one iteration's figure, decimals).
SPREAD_COLUMNS = (("Spearman per pixel (median)", lambda s: s.spearman, 2),
                  ("predicted / true (median)", lambda s: s.ratio, 2),
                  ("true SMAPE (median)", lambda s: s.true, 4))


def median_over_seeds(by_seed: dict[int, dict[str, list[IterationScore]]], iteration: int,
                      figure) -> list[float]:
    """One value per seed: the median over the scenes of `figure` at `iteration`."""
    return [statistics.median(figure(scores[iteration]) for scores in results.values())
            for results in by_seed.values()]


def seed_spread_table(by_seed: dict[int, dict[str, list[IterationScore]]]) -> str:
    """Per spp, each median over the scenes computed per seed, then the mean over seeds and their
    min–max: how much of a figure is the seed."""
    iterations = min(len(scores) for results in by_seed.values() for scores in results.values())
    lines = ["| spp | " + " | ".join(header for header, _, _ in SPREAD_COLUMNS) + " |",
             "|---:|" + "---:|" * len(SPREAD_COLUMNS)]
    for i in range(iterations):
        cells = []
        for _, figure, digits in SPREAD_COLUMNS:
            values = median_over_seeds(by_seed, i, figure)
            cells.append(f"{statistics.mean(values):.{digits}f} ({min(values):.{digits}f}–{max(values):.{digits}f})")
        spp = next(iter(next(iter(by_seed.values())).values()))[i].spp
        lines.append(f"| {spp:g} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _seed_section(by_seed: dict[int, dict[str, list[IterationScore]]] | None) -> str:
    if not by_seed or len(by_seed) < 2:
        return "One seed (0) was run: `--seeds 0 1 2` adds the spread over loop seeds."
    seeds = " ".join(str(s) for s in by_seed)
    return (f"The tables above are seed {next(iter(by_seed))}'s. Over the loop seeds {seeds} (`--seeds`): each figure "
            f"is the median over the scenes for one seed, then the mean over the {len(by_seed)} seeds and, in "
            "brackets, their minimum–maximum.\n\n" + seed_spread_table(by_seed))


def _ceiling_section(ceiling: dict[str, CeilingScore] | None) -> tuple[str, str]:
    """(the bound's header line, the section) — both say when the ceiling was not measured."""
    if not ceiling:
        return ("Bound: the repeatable ceiling was not measured in this run (`--ceiling-renders 0`).",
                "Not measured in this run.")
    first = next(iter(ceiling.values()))
    section = (f"Per scene, {first.renders} more renders at {first.spp:g} spp, each the loop above stopped after its "
               "first iteration with its own seed (from 1000 up, apart from the loop seeds). Repeatable ceiling: "
               f"the Spearman of the mean of {first.renders - 1} true error maps against the remaining one, "
               f"averaged over the {first.renders} leave-one-out choices: what a perfect predictor of the "
               "scene's expected error scores against one render (a little low: K − 1 maps estimate the "
               "expectation). Network: the error network's per-pixel Spearman against each render's own true "
               "map (the figure of the tables above), mean over the same renders, min–max in brackets. A "
               "predictor reads the render's own inputs and can see part of its noise, so the ceiling bounds "
               "predictors of the expected error, not every predictor. The ratio of the goal is the median "
               "scene's network Spearman over the median scene's ceiling.\n\n" + ceiling_table(ceiling))
    return ceiling_bound_line(ceiling), section


def write_calibration_report(results: dict[str, list[IterationScore]], out_dir: Path, weights: str,
                             suite: str = "dev", *, by_seed: dict[int, dict[str, list[IterationScore]]] | None = None,
                             ceiling: dict[str, CeilingScore] | None = None) -> Path:
    iterations = min(len(scores) for scores in results.values())
    spp_header = " | ".join(f"{next(iter(results.values()))[i].spp:g} spp" for i in range(iterations))
    medians = []
    for i in range(iterations):
        ratios = [scores[i].ratio for scores in results.values()]
        network = [scores[i].network_ratio for scores in results.values()]
        within = sum(abs(r - 1) <= MEAN_TOLERANCE for r in ratios)
        within_network = sum(abs(r - 1) <= MEAN_TOLERANCE for r in network)
        rho = statistics.median(scores[i].spearman for scores in results.values())
        rho_block = statistics.median(scores[i].block_spearman for scores in results.values())
        medians.append(f"| {results[next(iter(results))][i].spp:g} | {statistics.median(ratios):.2f} | "
                       f"{within} of {len(ratios)} | {statistics.median(network):.2f} | {within_network} of {len(network)} | "
                       f"{rho:.2f} | {rho_block:.2f} |")
    target_table = _target_table(results)
    bound, ceiling_text = _ceiling_section(ceiling)
    path = out_dir / REPORT_NAMES[suite]
    out_dir.mkdir(parents=True, exist_ok=True)
    path.write_text(fill(
        "calibration.md", provenance=provenance(variant=active_variant()), weights=weights, count=len(results),
        about=SUITES[suite].about,
        spp_header=spp_header, spp_rule="|".join(["---:"] * iterations), per_iteration=_per_iteration_table(results),
        medians="\n".join(medians), targets=target_table, bound=bound, ceiling=ceiling_text,
        seed_spread=_seed_section(by_seed), trusted=f"{TRUSTED:.0%}", tolerance=f"{MEAN_TOLERANCE:.0%}"))
    return path
