"""The raw image vs `mi.render`'s table (docs/sampler.md): each ratio carries its standard error
over the seeds, each row says where it stands against the 5 % bar, and a raw image that is not
hdrfilm's estimate is caught."""
from __future__ import annotations

import numpy as np
import pytest

from bench.raw_image_report import (QUALITY_FILTERS, QualityRow, TARGET_QUALITY_RATIO, quality_rows, quality_table,
                                    ratio_of_means, report_fields, seeds_text)
from bench.sampler_report import CASES, SamplerResult, write_sampler_report
from bench.stratified_pass_report import report_fields as stratified_fields


def test_the_ratios_standard_error_matches_the_spread_of_repeated_experiments():
    # 4000 repeated 8-seed experiments with per-seed relMSEs of known spread (cv 4 % and 2 %):
    # the formula's standard error of one experiment must match the spread of their ratios.
    rng = np.random.default_rng(1)
    ours = 1.03 * (1 + 0.04 * rng.standard_normal((4000, 8)))
    theirs = 1 + 0.02 * rng.standard_normal((4000, 8))
    ratios, errors = zip(*(ratio_of_means(tuple(o), tuple(t)) for o, t in zip(ours, theirs)))
    assert np.mean(ratios) == pytest.approx(1.03, abs=0.002)
    # √(0.04² + 0.02²)/√8 = 1.58 %: a missing /n (4.5 %) or /√n twice (0.56 %) falls outside
    assert np.std(ratios) == pytest.approx(1.03 * np.sqrt(0.04**2 + 0.02**2) / np.sqrt(8), rel=0.06)
    assert np.median(errors) == pytest.approx(np.std(ratios), rel=0.12)


def test_a_row_is_above_the_bar_only_when_it_clears_it_by_two_standard_errors():
    tight, wide = (0.99, 1.0, 1.01), (0.8, 1.0, 1.2)
    assert QualityRow("tent", 16, tight, tight, tight).verdict == "within"
    assert QualityRow("tent", 16, tuple(1.2 * x for x in tight), tight, tight).verdict == "above"
    row = QualityRow("tent", 16, tuple(1.07 * x for x in wide), wide, wide)
    assert row.ratio > TARGET_QUALITY_RATIO and row.verdict == "within noise"
    line = quality_table([row]).splitlines()[-1]
    assert f"**{row.ratio:.3f} ± {row.ratio_se:.3f}×** | within noise |" in line


def test_the_table_catches_a_raw_image_that_keeps_each_sample_in_its_own_pixel():
    # Scoring the per-pixel (FIS) estimate as the raw image, what the raw image was before the
    # splat: ~5× mi.render's relMSE under the Gaussian, far above the bar; the splat is not.
    kwargs = dict(size=32, spps=(16,), seeds={"gaussian": 3}, reference_spp=256)
    planted, = quality_rows(raw_of=lambda buffer: buffer.mean, **kwargs)
    assert planted.verdict == "above" and planted.ratio > 2, (planted.ratio, planted.ratio_se)
    real, = quality_rows(**kwargs)
    assert real.verdict != "above" and real.ratio < 1.3, (real.ratio, real.ratio_se)
    assert len(real.ours) == len(real.theirs) == 3 and np.isfinite(real.ratio_se)


def test_rows_follow_the_filters_order_with_each_filters_own_seeds():
    rows = quality_rows(size=8, spps=(2, 4), seeds={"mitchell": 3, "box": 2}, reference_spp=32)
    assert [(r.filter, r.spp, len(r.ours)) for r in rows] == [("box", 2, 2), ("box", 4, 2),
                                                             ("mitchell", 2, 3), ("mitchell", 4, 3)]
    assert list(QUALITY_FILTERS) == ["box", "tent", "gaussian", "mitchell"]


def test_the_sampler_page_fills_every_field_with_the_seeds_and_the_standard_errors(tmp_path):
    tight = (0.99, 1.0, 1.01)
    rows = [QualityRow("box", 16, tight, tight, tight), QualityRow("mitchell", 16, tight, tight, tight)]
    timing = SamplerResult(CASES[0], 8, 2, 1.0, 1.0, (1.0,))
    fields = {**report_fields(rows, [], 90.0), **stratified_fields([]), "mode_minutes": "9.5"}
    page = " ".join(write_sampler_report([timing], tmp_path, fields).read_text().split())
    assert seeds_text({"box": 8, "tent": 8, "mitchell": 16}) == "8 seeds (box, tent) and 16 (mitchell)"
    assert "6 seeds (box, tent, gaussian) and 24 (mitchell) for ours" in page
    assert "**1.000 ± 0.008×** | within |" in page
    assert "whole `--sampler` mode: 9.5 min" in page and "This section took 1.5 min" in page
    assert "a true 1.05 reads 1.047 there" in page  # the reference's 2048 spp beside 128
