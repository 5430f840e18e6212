"""What the splat costs (docs/sampler.md's last table): one row per film size, filter and spp."""
from __future__ import annotations

from bench.raw_image_report import COST_FILTERS, cost_rows, cost_table, report_fields


def test_the_cost_table_has_a_row_per_film_size_filter_and_spp_in_order():
    rows = cost_rows(cases=((8, (2, 3)), (16, (2,))), repeats=1)
    assert [(r.size, r.filter, r.spp) for r in rows] == (
        [(8, f, spp) for f in COST_FILTERS for spp in (2, 3)] + [(16, f, 2) for f in COST_FILTERS])
    assert all(r.samples == r.size * r.size * r.spp and r.with_splat_s > 0 and r.without_splat_s > 0 for r in rows)
    table = cost_table(rows).splitlines()
    assert len(table) == 2 + len(rows) and table[2].startswith("| 8² | tent | 2 |")
    assert table[-1].startswith("| 16² | mitchell | 2 |")
    assert report_fields([], rows)["cost_sizes"] == "128² and 512²"  # the sizes the report runs
