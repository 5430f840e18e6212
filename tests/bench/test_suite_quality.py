"""`renderloop bench --denoiser --suite dev`: a real run on the cheapest development scene
against its committed reference, and the crop finder."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from bench.quality_measures import mean_abs_change
from bench.suite_quality import CROP, ENERGY_TOLERANCE, _hardest_crop
from bench.suite_quality_report import run_suite_quality_report
from required_components import require_component


def test_hardest_crop_is_the_window_with_the_most_error():
    error = np.zeros((100, 120))
    error[70:80, 90:100] = 1.0
    rows, cols = _hardest_crop(error)
    assert rows.stop - rows.start == CROP and cols.stop - cols.start == CROP
    assert error[rows, cols].sum() == error.sum()


def test_suite_quality_report_scores_noisy_ours_and_oidn_at_every_sample_count(tmp_path: Path):
    require_component("pyoidn")
    text = run_suite_quality_report(tmp_path, only=["point_object"]).read_text()
    assert "$" not in text and "Command:" in text
    assert text.startswith("# The denoiser on the development suite:")
    rows = [line for line in text.splitlines() if line.startswith("| 16 |") or line.startswith("| 256 |")]
    per_method = [r for r in rows if r.count("|") == 7]  # the per-scene table: spp, method, 4 scores
    assert len(per_method) == 6
    for row in per_method:
        smape, relmse, psnr, energy = (float(c) for c in row.strip("|").split("|")[2:])
        assert all(math.isfinite(v) for v in (smape, relmse, psnr)) and abs(energy - 1) <= ENERGY_TOLERANCE, row
    assert (tmp_path / "suite-quality" / "point_object.png").stat().st_size > 0
    static = next(line for line in text.splitlines() if line.startswith("| point_object | static"))
    noisy, ours, oidn = (float(c) for c in static.strip("|").split("|")[2:5])
    assert noisy > ours > 0 and noisy > oidn > 0   # a static sequence: every frame its own seed
    assert "Static sequences: ours at most OIDN's flicker on" in text


def test_flicker_is_zero_for_identical_frames_and_the_mean_step_otherwise():
    frame = np.random.default_rng(0).random((4, 5, 3))
    assert mean_abs_change([frame, frame, frame]) == 0.0
    assert mean_abs_change([frame, frame + 0.2, frame, frame + 0.2]) == pytest.approx(0.2)
