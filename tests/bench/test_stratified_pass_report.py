"""Uneven stratified passes (docs/sampler.md): a scenes/dev scene as written and with the
`independent` sampler, timed on the same loop-like count maps."""
from __future__ import annotations

import numpy as np

from bench.stratified_pass_report import (SCENES_DIR, case_rows, independent_copy, loop_like_counts,
                                          report_fields)
from service.render.scenes import load_scene


def test_loop_like_counts_are_uneven_with_the_asked_mean():
    counts = loop_like_counts(32, 16, np.random.default_rng(0))
    assert counts.sum() == 32 * 32 * 16
    # uneven enough to need several sequence lengths (digits 0…5: 3…32 measured), within the
    # loop's 8× cap
    assert counts.min() < 8 and 32 <= counts.max() <= 8 * 16


def test_the_independent_copy_changes_only_the_sampler(tmp_path):
    scene_xml = SCENES_DIR / "dof_desk" / "scene.xml"
    copy = independent_copy(scene_xml, tmp_path / "dof_desk")
    assert load_scene(scene_xml, width=8, height=8).sensors()[0].sampler().class_name() == "StratifiedSampler"
    assert load_scene(copy, width=8, height=8).sensors()[0].sampler().class_name() == "IndependentSampler"
    assert copy.read_text().replace('type="independent"', 'type="stratified"') == scene_xml.read_text()


def test_each_pass_is_timed_both_ways_and_tabled():
    rows = case_rows("fine_texture", 16, (4, 8), repeats=1)
    assert [(r.scene, r.size, r.prior_spp) for r in rows] == [("fine_texture", 16, 4), ("fine_texture", 16, 8)]
    for r in rows:
        assert r.mean_spp == r.prior_spp and r.stratified_s > 0 and r.independent_s > 0
        assert r.launches >= 2   # uneven counts: more than one sequence length
        assert r.ratio == r.stratified_s / r.independent_s
    table = report_fields(rows)["stratified_table"].splitlines()
    assert len(table) == 2 + len(rows) and table[2].startswith("| fine_texture | 16² | 4 → 4 (")
