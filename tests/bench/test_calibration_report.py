"""The calibration report: where --target-error would stop, and a real run on the cheapest
development scene against its committed reference."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from bench.calibration_report import (IterationScore, fitted_change_scale, fitted_output_scale, run_calibration_report,
                                      stop_counts, stop_for_target, write_calibrated_error_network)
from bench.cli import main as bench_main
from bench.quality_measures import block_means
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
    text = run_calibration_report(tmp_path, only=["point_object"]).read_text()
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
