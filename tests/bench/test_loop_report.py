"""`renderloop bench --loop --quick` end to end (so the report code cannot rot), plus the
log-log reading of time-to-target that the headline rests on."""
from __future__ import annotations

import csv
import math
import statistics
from pathlib import Path

import numpy as np
import pytest
import torch

from bench.common import METRIC_NAMES as METRICS
from bench.cli import main as bench_main
from bench.common import true_error_map
from bench import loop_report
from bench.loop_report import run_loop_benchmark
from bench.loop_run import (DEFAULT_METHODS, STAGES, ErrorAgreement, Headline, TrueErrorMap, select_methods,
                             time_to_reach)
from bench.loop_seeds import bound_line, gaps, seed_table


def test_quick_loop_benchmark_writes_a_finite_report(tmp_path: Path, tiny_weights_dir: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    # The HTTP λ micro-benchmark's server on the thread backend (RENDERLOOP_CONCURRENCY, read by
    # service.api.serve.app_from_env in the server process): the report's plumbing is under test,
    # not Ray, and a local Ray start was most of this test's time (tests/service cover Ray's λ path).
    monkeypatch.setenv("RENDERLOOP_CONCURRENCY", "1")
    # The models micro-benchmark spawns one fresh torch process per case (seconds each): one case
    # pins its section here; every case runs in tests/bench/test_models_report.py.
    monkeypatch.setattr(loop_report, "MODEL_CASES", ("lambda-tail",))
    report = run_loop_benchmark(tmp_path / "docs", quick=True, weights_dir=tiny_weights_dir, cache_dir=tmp_path / "cache",
                                command="renderloop bench --loop --quick")
    text = report.read_text()
    for needed in ("Command: `renderloop bench --loop --quick`", "Machine:", "Date:", "## Headline", "**median**",
                   "## Micro-benchmarks", "p50", "ms / megapixel",
                   "sums of per-stage minimums", "marks a time extrapolated", "Measured at the start of this run",
                   "the faster count ran everything",
                   "cornell-box / path / box", "quality high", "| lambda-tail | 32² |", "λ tail latency"):
        assert needed in text
    assert "$" not in text  # every template field was filled
    assert "Failed:" not in text  # every micro-benchmark ran, the HTTP one against a real server included
    rows = list(csv.DictReader(open(tmp_path / "docs" / "benchmarks" / "loop-quick.csv")))
    methods = {r["method"] for r in rows}
    assert {"a", "b", "c", "d", "o"} <= methods
    assert "with a perfect error map (o) the same allocation would reach a median SMAPE (o)/(b)" in text
    assert "## Against the bound, over seeds" in text and "One loop seed (0) and every method" in text
    assert len({r["scene"] for r in rows}) == 2
    for r in rows:
        for column in (*METRICS, *(f"{s}_s" for s in STAGES), "cumulative_s"):
            assert math.isfinite(float(r[column])), (column, r)
    assert sorted({float(r["spp_mean"]) for r in rows}) == [16, 32, 64]
    for png in ("error_vs_time.png", "spp_maps.png", "error_maps.png"):
        assert (tmp_path / "docs" / "benchmarks" / png).stat().st_size > 0
    # References are cached on disk (one per scene), so later runs do not render them again.
    assert len(list((tmp_path / "cache" / "references").glob("*.npz"))) == 2


def test_development_suite_loop_benchmark_scores_against_the_committed_reference(
        tmp_path: Path, tiny_weights_dir: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # The thread probe of a suite at each scene's own size runs at THREAD_PROBE_SIZE (256²: about
    # half of this test's time); a smaller side exercises the same probe and report line.
    monkeypatch.setattr(loop_report, "THREAD_PROBE_SIZE", 48)
    report = run_loop_benchmark(tmp_path / "docs", weights_dir=tiny_weights_dir, cache_dir=tmp_path / "cache",
                                suite="dev", only=["point_object"], command="renderloop bench --loop --suite dev",
                                seeds=(0, 1), methods=["b", "d", "o"])
    text = report.read_text()
    # only some methods: its own report, never over the every-method benchmarks-dev.md
    assert report.name == "benchmarks-dev-bdo.md" and "$" not in text
    assert not (tmp_path / "docs" / "benchmarks-dev.md").exists()
    assert "each scene's own film size" in text and "| point_object |" in text
    assert text.startswith("# What accuracy costs in time: the render loop benchmark at each scene's own film size")
    assert "one single-frame 48² denoise took" in text and "probe failed" not in text  # threads chosen by measuring
    # the allocation bound over both seeds, and which methods ran
    assert "**Bound: the loop's SMAPE at equal samples within 0.02 of the true-error allocation (o)" in text
    assert "Loop seeds 0, 1 (`--seeds`), only (b), (d), (o)" in text and "| (e) s |" not in text
    seed_row = next(line for line in text.splitlines() if line.startswith("| point_object | 0.") and "±" in line)
    assert len(seed_row.split("±")) == 4, seed_row  # (d)/(b), (o)/(b), gap
    rows = list(csv.DictReader(open(tmp_path / "docs" / "benchmarks-dev-bdo" / "loop.csv")))
    assert {r["scene"] for r in rows} == {"point_object"} and {r["seed"] for r in rows} == {"0", "1"}
    assert {r["method"] for r in rows} == {"b", "d", "o"}
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


def _head(d_b: dict[str, float], o_b: dict[str, float]) -> Headline:
    """A headline carrying only what the allocation bound reads: (d)/(b) and (o)/(b) per scene."""
    median = lambda ratios: statistics.median(ratios.values()) if ratios else math.nan
    return Headline({}, {}, {}, {}, d_b, median(d_b), o_b, median(o_b))


SEED_HEADS = {  # three scenes, two seeds: per-scene gaps 0.05/0.01/0.03, then 0.03/0.01/0.01
    0: _head({"a": 0.90, "b": 0.80, "c": 0.95}, {"a": 0.85, "b": 0.79, "c": 0.92}),
    1: _head({"a": 0.88, "b": 0.82, "c": 0.93}, {"a": 0.85, "b": 0.81, "c": 0.92}),
}


def test_the_seed_table_gives_each_ratio_and_the_gap_as_mean_sd_and_min_max_over_seeds() -> None:
    table = seed_table(SEED_HEADS)
    sd = statistics.stdev([0.05, 0.03])
    # scene a: (d)/(b) 0.90 and 0.88; gap 0.05 and 0.03
    assert f"| a | 0.890 ± {statistics.stdev([0.90, 0.88]):.3f} (0.880–0.900) | 0.850 ± 0.000 (0.850–0.850) | " \
           f"0.040 ± {sd:.3f} (0.030–0.050) |" in table
    # the median scene per seed: gaps median 0.03 (seed 0) and 0.01 (seed 1) → 0.020 ± 0.014
    median_row = next(line for line in table.splitlines() if line.startswith("| **median** |"))
    assert f"**0.020 ± {statistics.stdev([0.03, 0.01]):.3f} (0.010–0.030)**" in median_row
    # (d)/(b) medians 0.90 and 0.88; (o)/(b) 0.85 twice: the gap is the median scene's, not 0.89 − 0.85
    assert median_row.startswith(f"| **median** | **0.890 ± {statistics.stdev([0.90, 0.88]):.3f} (0.880–0.900)** | "
                                 "**0.850 ± 0.000 (0.850–0.850)** |")
    assert gaps(SEED_HEADS[0]) == pytest.approx({"a": 0.05, "b": 0.01, "c": 0.03})


def test_the_bound_line_says_met_only_when_the_median_gap_is_within_two_hundredths() -> None:
    line = bound_line(SEED_HEADS)  # mean of the per-seed median gaps: 0.020
    assert "within 0.02 of the true-error allocation (o) on the median scene" in line
    assert "**0.020 ± 0.014 (0.010–0.030)** (mean ± s.d. over seeds 0, 1, min–max in brackets; met)" in line
    wide = {0: _head({"a": 0.90}, {"a": 0.85})}  # one seed: no s.d., gap 0.05
    assert "**0.050 (0.050–0.050)** (mean ± s.d. over seeds 0, min–max in brackets; not met)" in bound_line(wide)
    assert "was not run" in bound_line({0: _head({"a": 0.9}, {})})


def test_methods_must_be_known_and_include_the_product() -> None:
    assert [m.key for m in select_methods(["o", "b", "d"])] == ["b", "d", "o"]  # in METHODS' order
    # the replicated bound (x) costs four loops: only when named
    assert select_methods(None) == DEFAULT_METHODS and "x" not in {m.key for m in DEFAULT_METHODS}
    assert [m.key for m in select_methods(["x", "d"])] == ["d", "x"]
    with pytest.raises(ValueError, match="product"):
        select_methods(["b", "o"])
    with pytest.raises(ValueError, match="unknown"):
        select_methods(["b", "d", "z"])


def test_loop_flags_refuse_a_method_set_without_the_product_and_zero_timing_repeats(capsys) -> None:
    assert bench_main(["--loop", "--methods", "b", "o"]) == 2
    assert "must include the product (d)" in capsys.readouterr().err
    assert bench_main(["--loop", "--timing-repeats", "0"]) == 2
    assert "--timing-repeats must be >= 1" in capsys.readouterr().err


def test_a_scene_note_speaks_of_uniform_convergence_only_when_the_run_had_uniform():
    with_a = loop_report.agreement_line(ErrorAgreement("cbox", 20, 100.0, 300, 0.6, 1.1, -0.48))
    without_a = loop_report.agreement_line(ErrorAgreement("cbox", 20, 100.0, 300, 0.6, 1.1, math.nan))
    assert "(a) converges as SMAPE ∝ spp^-0.48" in with_a
    assert "converges" not in without_a and "nan" not in without_a and without_a.endswith("= 1.1.")
