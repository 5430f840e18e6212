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
TRUSTED = 0.25  # issue 14: the true SMAPE at a target-error stop within 25 % of the target
MEAN_TOLERANCE = 0.20  # issue 14: predicted mean within 20 % of the true mean
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
    spearman: float  # per pixel: the figure issue 14 asks ≥ 0.7 of
    block_spearman: float = float("nan")  # of RANKING_BLOCK² tile means
    network: float = float("nan")  # the error network's own mean, before the change calibration
    change: float = float("nan")    # mean SMAPE between this iteration's denoised image and the last one's

    @property
    def ratio(self) -> float:
        return self.predicted / self.true if self.true > 0 else float("nan")

    @property
    def network_ratio(self) -> float:
        return self.network / self.true if self.true > 0 else float("nan")


def score_scene(path: Path, reference, networks) -> list[IterationScore]:
    # Run as a job that stops on a target error runs (its first iteration in two halves, so that
    # mean is calibrated too: RenderLoop._splits_first_iteration), with a target no scene reaches:
    # until it stops, a loop with any target E does exactly this, so these records say where E stops.
    spec = LoopSpec(scene=str(path), max_iterations=ITERATIONS, allocator="error", target_error=UNREACHED_TARGET)
    scores, previous = [], None
    for record in RenderLoop(spec, networks).run():
        denoised, predicted = record.denoised[0], record.error[0]
        true = true_error_map(denoised, reference)
        scores.append(IterationScore(record.spp_mean, float(predicted.mean()),
                                     image_metrics(denoised, reference)["smape"], spearman(predicted, true),
                                     spearman(block_means(predicted, RANKING_BLOCK), block_means(true, RANKING_BLOCK)),
                                     network=record.network_error,
                                     change=float("nan") if previous is None else image_change(previous, denoised)))
        previous = denoised
    return scores


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
                           suite: str = "dev", fit_scale_to: Path | None = None) -> Path:
    """Measure and write the report; with `fit_scale_to`, also write the calibrated error network there."""
    nets = load_bench_networks(weights_dir)
    results: dict[str, list[IterationScore]] = {}
    with pinned_torch_threads(TORCH_THREADS):
        for scene in dev_scenes(only, SUITES[suite].root):
            reference, _ = load_reference(SUITES[suite].references, scene, None if scene.frames == 1 else 0)
            results[scene.name] = score_scene(scene.path, reference, nets.networks)
            last = results[scene.name][-1]
            print(f"bench --calibration: {scene.name}: predicted {last.predicted:.4f} true {last.true:.4f} "
                  f"spearman {last.spearman:.2f}", flush=True)
    if fit_scale_to is not None:
        scale = fitted_output_scale(results)
        change_scale = fitted_change_scale(results, scale)
        command = (f"renderloop bench --calibration --suite {suite} --weights {nets.folder} --fit-scale {fit_scale_to}"
                   + (f" --only {' '.join(only)}" if only else ""))
        written = write_calibrated_error_network(nets.folder, fit_scale_to, scale, command, change_scale)
        print(f"bench --calibration: output scale ×{scale:.4f}, change scale {change_scale:.4f} → {written}", flush=True)
    return write_calibration_report(results, out_dir, nets.description, suite)


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


def write_calibration_report(results: dict[str, list[IterationScore]], out_dir: Path, weights: str,
                             suite: str = "dev") -> Path:
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
    path = out_dir / REPORT_NAMES[suite]
    out_dir.mkdir(parents=True, exist_ok=True)
    path.write_text(fill(
        "calibration.md", provenance=provenance(variant=active_variant()), weights=weights, count=len(results),
        about=SUITES[suite].about,
        spp_header=spp_header, spp_rule="|".join(["---:"] * iterations), per_iteration=_per_iteration_table(results),
        medians="\n".join(medians), targets=target_table, trusted=f"{TRUSTED:.0%}", tolerance=f"{MEAN_TOLERANCE:.0%}"))
    return path
