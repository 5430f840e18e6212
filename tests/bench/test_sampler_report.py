"""The throughput comparison runs over (scene, integrator, filter) cases; the first one renders
end to end in the loop report's test."""
from __future__ import annotations

from bench.sampler_report import CASES, bench_case


def test_cases_cover_path_volpath_and_direct_with_the_box_filter():
    assert {case.integrator for case in CASES} >= {"path", "volpath", "direct"}
    assert {case.filter for case in CASES} == {"box"}


def test_one_case_times_both_renderers_at_equal_samples():
    result = bench_case(CASES[0], size=8, spp=2, repeats=1)
    assert result.samples == 8 * 8 * 2 and len(result.ratios) == 1
    assert result.ours_s > 0 and result.mi_render_s > 0 and result.ratio > 0
