"""The calibration report: where --target-error would stop, and a real run on the cheapest
development scene against its committed reference."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from bench.calibration_ceiling import (CeilingScore, FirstIterationMaps, ceiling_bound_line, ceiling_score, ceiling_table,
                                       leave_one_out_spearman, scene_ceiling)
from bench.calibration_report import (IterationScore, seed_spread_table, fitted_change_scale, fitted_output_scale, run_calibration_report,
                                      stop_counts, stop_for_target, write_calibrated_error_network)
from bench.cli import main as bench_main
from bench.quality_measures import block_means, spearman
from models.checkpoint import read_checkpoint, save_checkpoint
from models.error_predictor import ErrorPredictor, ErrorPredictorConfig
from models.pretrained import ERROR_PREDICTOR_FILE
from tests.models.conftest import PLAIN_ERROR_NETWORK
from service.loop.change_calibration import calibrated_mean


def test_target_error_stop_is_the_first_iteration_predicted_at_or_below_it():
    scores = [IterationScore(16, 0.05, 0.04, 0.5), IterationScore(32, 0.03, 0.035, 0.5),
              IterationScore(64, 0.02, 0.02, 0.5)]
    assert stop_for_target(scores, 0.03).spp == 32  # at or below
    assert stop_for_target(scores, 0.06).spp == 16
    assert stop_for_target(scores, 0.01) is None  # never reached


def test_stop_counts_separate_stops_the_first_pass_already_overshot():
    results = {
        "easy": [IterationScore(16, 0.03, 0.01, 0.5), IterationScore(32, 0.02, 0.008, 0.5)],    # 16 spp, 0.25× E
        "right": [IterationScore(16, 0.08, 0.07, 0.5), IterationScore(32, 0.035, 0.04, 0.5)],  # 32 spp, 1.0× E
        "close": [IterationScore(16, 0.035, 0.036, 0.5)],                                       # 16 spp, 0.9× E
        "never": [IterationScore(16, 0.09, 0.08, 0.5), IterationScore(32, 0.06, 0.05, 0.5)],
    }
    counts = stop_counts(results, 0.04)
    assert (counts.stops, counts.trusted, counts.first, counts.first_below) == (3, 2, 2, 1)


def test_calibration_report_scores_every_iteration_against_the_reference(tmp_path: Path):
    text = run_calibration_report(tmp_path, only=["point_object"], ceiling_renders=4).read_text()
    row = next(line for line in text.splitlines() if line.startswith("| point_object |"))
    cells = row.strip("|").split("|")[1:]
    assert len(cells) == 5  # 16 → 256 spp
    for cell in cells:
        predicted, rest = cell.split("/")
        true, rho = rest.split("(")
        # the shipped error network ranks point_object's pixels at Spearman 0.88–0.90 from 16 to 256
        # spp (a map ranked against the wrong image, or the per-image ρ of a shuffled map, breaks it)
        assert float(predicted) > 0 and float(true) > 0 and float(rho.rstrip(") ")) > 0.6, cell
    assert "Command:" in text and math.isfinite(float(cells[-1].split("/")[0]))
    median_row = next(line for line in text.splitlines() if line.startswith("| 256 |"))
    tiles = float(median_row.strip("|").split("|")[-1])
    assert tiles > 0.6, tiles   # measured 0.93 (8×8 tiles at 256 spp)
    # the repeatable ceiling from 4 more 16-spp first iterations: measured 0.98, the network 0.90 on them
    assert "**Bound: the error network's per-pixel Spearman ≥ 90% of the repeatable ceiling**" in text
    ceiling_row = next(line for line in text.splitlines() if line.startswith("| point_object | 0.") and "–" in line)
    ceiling, network = (float(cell.split("(")[0]) for cell in ceiling_row.strip("|").split("|")[1:3])
    assert 0.9 < ceiling <= 1 and 0.6 < network <= ceiling, ceiling_row
    assert "One seed (0) was run" in text


def test_ceiling_renders_outside_four_to_eight_are_refused(capsys):
    assert bench_main(["--calibration", "--ceiling-renders", "3"]) == 2
    assert "--ceiling-renders takes 4–8" in capsys.readouterr().err


def test_fitted_output_scale_makes_the_networks_median_ratio_one_and_skips_empty_iterations():
    def score(network: float, true: float) -> IterationScore:  # the loop's mean set apart: the fit reads the network's
        return IterationScore(16, 1.0, true, 0.5, network=network)
    results = {"a": [score(0.02, 0.04), score(0.01, 0.0)], "b": [score(0.03, 0.03)], "c": [score(0.01, 0.04)]}
    # ratios 0.5, 1.0, 0.25 (the true-0 iteration has no ratio): median 0.5 → ×2
    assert fitted_output_scale(results) == 2.0


def test_fitted_change_scale_makes_the_calibrated_median_ratio_one_after_the_output_scale():
    # √(2P · s · C) = T on the middle iteration: P = 0.01, C = 0.005, T = 0.02 → s = 0.0004 / 0.0001 = 4
    results = {"a": [IterationScore(16, 0.0, 0.05, 0.5, network=0.03),  # first iteration: no change, skipped
                     IterationScore(32, 0.0, 0.02, 0.5, network=0.01, change=0.005)],
               "b": [IterationScore(32, 0.0, 0.01, 0.5, network=0.01, change=0.005)],   # ratio ½ of "a"'s
               "c": [IterationScore(32, 0.0, 0.04, 0.5, network=0.01, change=0.005)]}   # ratio 2×
    scale = fitted_change_scale(results, 2.0)
    assert scale == pytest.approx(4.0)
    assert calibrated_mean(2.0 * 0.01, 0.005, scale) == pytest.approx(0.02)
    with pytest.raises(ValueError, match="change"):
        fitted_change_scale({"a": results["a"][:1]}, 1.0)


def test_calibrated_error_network_carries_the_scale_and_the_command(tmp_path: Path):
    source, target = tmp_path / "src", tmp_path / "dst"
    model = ErrorPredictor(ErrorPredictorConfig(width=4, blocks=1, **{**PLAIN_ERROR_NETWORK, "output_scale": 1.2}))
    save_checkpoint(source / ERROR_PREDICTOR_FILE, model, {"command": "renderloop train …"})
    write_calibrated_error_network(source, target, 1.5, "renderloop bench --calibration --suite val", 1.3)
    written = read_checkpoint(target / ERROR_PREDICTOR_FILE)
    assert written["config"]["output_scale"] == pytest.approx(1.8)
    assert written["config"]["change_scale"] == pytest.approx(1.3)
    assert "change_scale 1.3000" in written["extra"]["calibration"]
    assert written["extra"]["command"] == "renderloop train …"
    assert "--suite val" in written["extra"]["calibration"]


def test_fit_scale_is_refused_outside_the_validation_scenes(capsys):
    assert bench_main(["--calibration", "--fit-scale", "somewhere"]) == 2
    assert "--suite val" in capsys.readouterr().err


def test_block_means_average_each_tile_and_drop_the_ragged_edge():
    x = np.arange(6 * 9, dtype=float).reshape(6, 9)
    means = block_means(x, 3)
    assert means.shape == (2, 3)
    assert means[1, 2] == x[3:6, 6:9].mean()
    image = np.arange(5 * 7 * 3, dtype=float).reshape(5, 7, 3)   # channels kept apart
    pooled = block_means(image, 2)
    assert pooled.shape == (2, 3, 3)
    np.testing.assert_allclose(pooled[1, 2], image[2:4, 4:6].mean((0, 1)))


def _noisy_maps(expected: np.ndarray, noise: float, renders: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.stack([expected + noise * rng.standard_normal(expected.shape) for _ in range(renders)])


def test_the_ceiling_of_identical_maps_is_one_and_of_pure_noise_about_zero():
    expected = np.random.default_rng(1).random((32, 32))
    assert leave_one_out_spearman(np.stack([expected] * 4)) == pytest.approx(1.0)
    noise_only = _noisy_maps(np.zeros((32, 32)), 1.0, 8)
    assert abs(leave_one_out_spearman(noise_only)) < 0.1
    with pytest.raises(ValueError, match="two maps"):
        leave_one_out_spearman(noise_only[:1])


def test_the_ceiling_is_the_mean_leave_one_out_spearman_under_additive_noise():
    # map = expected + noise of equal variance: one map against the mean of K − 1 others correlates
    # as 1 / √((1 + r)(1 + r / (K − 1))) with r = 1 (Pearson; Spearman of Gaussians is close to it)
    expected = np.random.default_rng(2).standard_normal((64, 64))
    maps = _noisy_maps(expected, 1.0, 8, seed=3)
    assert leave_one_out_spearman(maps) == pytest.approx(1 / math.sqrt(2 * (1 + 1 / 7)), abs=0.03)
    by_hand = np.mean([spearman(np.delete(maps, k, axis=0).mean(axis=0), maps[k]) for k in range(8)])
    assert leave_one_out_spearman(maps) == pytest.approx(by_hand)


def test_ceiling_score_ranks_the_predictions_against_each_renders_own_map():
    expected = np.random.default_rng(4).random((16, 16))
    maps = [FirstIterationMaps(true, expected) for true in _noisy_maps(expected, 0.3, 4, seed=5)]
    score = ceiling_score(16, maps)
    each = [spearman(expected, m.true) for m in maps]
    assert score.network == pytest.approx(np.mean(each)) and score.network_min == pytest.approx(min(each))
    assert score.renders == 4 and score.ratio == pytest.approx(score.network / score.ceiling)
    with pytest.raises(ValueError, match="4–8"):
        scene_ceiling(lambda seed: (16, maps[0]), 3)


def test_the_ceiling_bound_line_and_table_state_the_median_ratio_against_the_goal():
    scores = {"a": CeilingScore(16, 8, 0.80, 0.76), "b": CeilingScore(16, 8, 0.70, 0.56), "c": CeilingScore(16, 8, 0.40, 0.40)}
    line = ceiling_bound_line(scores)
    # median network 0.56 / median ceiling 0.70 = 80 % < 90 %
    assert "median network 0.56 / median ceiling 0.70 = **80%** (not met)" in line and "≥ 90% of" in line
    assert "(met)" in ceiling_bound_line({"a": CeilingScore(16, 8, 0.70, 0.65)})  # 93 %
    table = ceiling_table(scores)
    assert "| **median** | **0.70** | **0.56** | **80%** |" in table
    assert "| b | 0.70 | 0.56 (nan–nan) | 80% |" in table


def test_seed_spread_gives_each_seeds_median_as_mean_and_min_max():
    def run(rho: float, true: float) -> list[IterationScore]:
        return [IterationScore(16, true, true, rho)]
    by_seed = {0: {"a": run(0.5, 0.01), "b": run(0.7, 0.03), "c": run(0.9, 0.02)},   # median ρ 0.7, true 0.02
               1: {"a": run(0.4, 0.01), "b": run(0.6, 0.05), "c": run(0.5, 0.04)}}   # median ρ 0.5, true 0.04
    table = seed_spread_table(by_seed)
    assert "| 16 | 0.60 (0.50–0.70) | 1.00 (1.00–1.00) | 0.0300 (0.0200–0.0400) |" in table
