"""`renderloop bench --denoiser --suite dev`: a real run on the cheapest development scene
against its committed reference, and the crop finder."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from bench.common import load_bench_networks, oidn_denoiser
from bench.dev_references import DEFAULT_REFERENCE_DIR, dev_scenes, load_reference
from bench.quality_measures import mean_abs_change
from bench.suite_quality import CROP, ENERGY_TOLERANCE, STATIC_FRAMES, _hardest_crop, temporal_flicker
from bench.suite_quality_report import run_suite_quality_report
from models.denoiser import Denoiser
from models.pretrained import Networks
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


def hard_shadows_flicker(networks) -> dict[str, float]:
    require_component("pyoidn")
    scene = dev_scenes(["hard_shadows"])[0]
    reference, _ = load_reference(DEFAULT_REFERENCE_DIR, scene)
    return temporal_flicker(scene, [reference] * STATIC_FRAMES, networks, oidn_denoiser()[0])


def flicker_failures(result: dict[str, float]) -> list[str]:
    """Issue 13's flicker guard on a static sequence: steadier than OIDN frame by frame, with no
    more error than OIDN on the very input our network filtered (the window's pooled samples) —
    the pooling alone makes any network of the shipped architecture steadier, trained or not."""
    failures = []
    if not result["kpcn"] < 0.8 * result["oidn"]:
        failures.append(f"flicker {result['kpcn']:.5f} not below 0.8 × OIDN's {result['oidn']:.5f}")
    if not result["smape_kpcn"] <= result["smape_oidn_pooled"]:
        failures.append(f"SMAPE {result['smape_kpcn']:.5f} above OIDN's on the pooled input {result['smape_oidn_pooled']:.5f}")
    return failures


def test_a_static_sequence_is_denoised_over_its_window_and_flickers_less_than_oidn_per_frame():
    """Issue 13: flicker on a static sequence ≤ OIDN's. Denoised frame by frame, the shipped
    network flickered 1 % more than OIDN on hard_shadows (0.00448 vs 0.00444); over its window
    (models.accumulation) it must flicker less, with no more error. Measured: flicker 0.00185
    (OIDN 0.00444), SMAPE 0.01202 (OIDN on the pooled input 0.01209)."""
    result = hard_shadows_flicker(load_bench_networks(None).networks)
    assert flicker_failures(result) == []
    assert result["oidn_pooled"] < result["oidn"] < result["noisy"]   # the pooled input itself is steadier


def test_an_untrained_network_of_the_shipped_architecture_fails_the_flicker_guard():
    """Planted: the same flicker (0.00185), but SMAPE 0.01219 against OIDN pooled 0.01209 (seed 0)."""
    shipped = load_bench_networks(None).networks
    torch.manual_seed(0)
    untrained = Networks(Denoiser(shipped.denoiser.config).eval(), shipped.error_predictor)
    assert [f.split(" ")[0] for f in flicker_failures(hard_shadows_flicker(untrained))] == ["SMAPE"]


def test_flicker_is_zero_for_identical_frames_and_the_mean_step_otherwise():
    frame = np.random.default_rng(0).random((4, 5, 3))
    assert mean_abs_change([frame, frame, frame]) == 0.0
    assert mean_abs_change([frame, frame + 0.2, frame, frame + 0.2]) == pytest.approx(0.2)
