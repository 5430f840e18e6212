"""`renderloop bench --loop --quick` end to end (so the report code cannot rot), plus the
log-log reading of time-to-target that the headline rests on."""
from __future__ import annotations

import csv
import importlib.util
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from bench.common import METRIC_NAMES as METRICS
from bench.common import true_error_map
from bench.loop_report import run_loop_benchmark
from bench.loop_run import STAGES, TrueErrorMap, time_to_reach


def test_quick_loop_benchmark_writes_a_finite_report(tmp_path: Path, tiny_weights_dir: Path) -> None:
    report = run_loop_benchmark(tmp_path / "docs", quick=True, weights_dir=tiny_weights_dir, cache_dir=tmp_path / "cache",
                                command="renderloop bench --loop --quick")
    text = report.read_text()
    for needed in ("Command: `renderloop bench --loop --quick`", "Machine:", "Date:", "## Headline", "**median**",
                   "## Micro-benchmarks", "p50", "ms / megapixel",
                   "sums of per-stage minimums", "marks a time extrapolated", "Measured at the start of this run",
                   "the faster count ran everything",
                   "cornell-box / path / box", "quality high"):
        assert needed in text
    assert "$" not in text  # every template field was filled
    assert "Failed:" not in text  # every micro-benchmark ran, the HTTP one against a real server included
    rows = list(csv.DictReader(open(tmp_path / "docs" / "benchmarks" / "loop-quick.csv")))
    methods = {r["method"] for r in rows}
    assert {"a", "b", "c", "d", "o"} <= methods
    assert "with a perfect error map (o) the same allocation would reach a median SMAPE (o)/(b)" in text
    assert len({r["scene"] for r in rows}) == 2
    for r in rows:
        for column in (*METRICS, *(f"{s}_s" for s in STAGES), "cumulative_s"):
            assert math.isfinite(float(r[column])), (column, r)
    assert sorted({float(r["spp_mean"]) for r in rows}) == [16, 32, 64]
    for png in ("error_vs_time.png", "spp_maps.png", "error_maps.png"):
        assert (tmp_path / "docs" / "benchmarks" / png).stat().st_size > 0
    # References are cached on disk (one per scene), so later runs do not render them again.
    assert len(list((tmp_path / "cache" / "references").glob("*.npz"))) == 2


def test_development_suite_loop_benchmark_scores_against_the_committed_reference(tmp_path: Path,
                                                                                tiny_weights_dir: Path) -> None:
    report = run_loop_benchmark(tmp_path / "docs", weights_dir=tiny_weights_dir, cache_dir=tmp_path / "cache",
                                suite="dev", only=["point_object"], command="renderloop bench --loop --suite dev")
    text = report.read_text()
    assert report.name == "benchmarks-dev.md" and "$" not in text
    assert "each scene's own film size" in text and "| point_object |" in text
    assert text.startswith("# What accuracy costs in time: the render loop benchmark at each scene's own film size")
    assert "one single-frame 256² denoise took" in text and "probe failed" not in text  # threads chosen by measuring
    if importlib.util.find_spec("pyoidn") is not None:
        assert "uniform + OIDN at equal wall time on" in text
    rows = list(csv.DictReader(open(tmp_path / "docs" / "benchmarks-dev" / "loop.csv")))
    assert {r["scene"] for r in rows} == {"point_object"}
    assert sorted({float(r["spp_mean"]) for r in rows}) == [16, 32, 64, 128]
    assert all(math.isfinite(float(r["smape"])) for r in rows)
    assert not (tmp_path / "cache" / "references").exists()  # the committed reference, nothing rendered


def test_the_bound_method_allocates_by_the_denoised_images_true_error() -> None:
    rng = np.random.default_rng(0)
    reference = rng.random((6, 8, 3)).astype(np.float32)
    denoised = rng.random((6, 8, 3)).astype(np.float32)
    tensor = torch.from_numpy(denoised).permute(2, 0, 1)[None]
    error = TrueErrorMap(reference)(None, tensor)
    assert error.shape == (1, 1, 6, 8)
    np.testing.assert_allclose(error[0, 0].numpy(), true_error_map(denoised, reference), rtol=1e-6)


def test_time_to_reach_interpolates_in_log_log() -> None:
    # SMAPE ∝ t^-1/2: from 0.4 at 1 s to 0.2 at 4 s, so 0.2828 is reached at 2 s.
    seconds, how = time_to_reach([1.0, 4.0], [0.4, 0.2], 0.4 / math.sqrt(2))
    assert how == "interpolated" and seconds == pytest.approx(2.0)


def test_time_to_reach_flags_bounds_and_extrapolation() -> None:
    assert time_to_reach([1.0, 4.0], [0.1, 0.05], 0.2) == (1.0, "first iteration")
    seconds, how = time_to_reach([1.0, 4.0], [0.4, 0.2], 0.1)
    assert how == "extrapolated" and seconds == pytest.approx(16.0)
    assert time_to_reach([1.0, 4.0], [0.4, 0.5], 0.1) == (math.inf, "not reached")
    assert time_to_reach([], [], 0.1) == (math.inf, "not reached")
    # a nearly flat last segment: no extrapolated age (it overflowed float before)
    assert time_to_reach([0.016, 0.025], [0.25509, 0.25477], 0.0104) == (math.inf, "not reached")
