"""The throughput comparison runs over (scene, integrator, filter) cases, each built and timed."""
from __future__ import annotations

import pytest

from bench.sampler_report import CASES, bench_case


def test_cases_cover_path_volpath_and_direct_each_with_box_and_an_importance_sampled_filter():
    for integrator in ("path", "volpath", "direct"):
        filters = {case.filter for case in CASES if case.integrator == integrator}
        assert "box" in filters and filters - {"box"}, (integrator, filters)


@pytest.mark.parametrize("case", CASES, ids=lambda case: case.label)
def test_every_case_times_both_renderers_at_equal_samples(case):
    result = bench_case(case, size=8, spp=2, repeats=1)
    assert result.samples == 8 * 8 * 2 and len(result.ratios) == 1
    # one run: the ratio is mi.render's time over ours (a swapped ratio inverts every headline figure)
    assert result.ratio == pytest.approx(result.mi_render_s / result.ours_s) and result.ours_s > 0
