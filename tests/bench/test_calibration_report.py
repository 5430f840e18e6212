"""The calibration report: where --target-error would stop, and a real run on the cheapest
development scene against its committed reference."""
from __future__ import annotations

import math
from pathlib import Path

from bench.calibration_report import IterationScore, run_calibration_report, stop_for_target


def test_target_error_stop_is_the_first_iteration_predicted_at_or_below_it():
    scores = [IterationScore(16, 0.05, 0.04, 0.5), IterationScore(32, 0.03, 0.035, 0.5),
              IterationScore(64, 0.02, 0.02, 0.5)]
    assert stop_for_target(scores, 0.03).spp == 32  # at or below
    assert stop_for_target(scores, 0.06).spp == 16
    assert stop_for_target(scores, 0.01) is None  # never reached


def test_calibration_report_scores_every_iteration_against_the_reference(tmp_path: Path):
    text = run_calibration_report(tmp_path, only=["point_object"]).read_text()
    row = next(line for line in text.splitlines() if line.startswith("| point_object |"))
    cells = row.strip("|").split("|")[1:]
    assert len(cells) == 5  # 16 → 256 spp
    for cell in cells:
        predicted, rest = cell.split("/")
        true, rho = rest.split("(")
        assert float(predicted) > 0 and float(true) > 0 and -1 <= float(rho.rstrip(") ")) <= 1
    assert "Command:" in text and math.isfinite(float(cells[-1].split("/")[0]))
