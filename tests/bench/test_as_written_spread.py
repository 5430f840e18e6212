"""docs/as-written.md over several seeds: beside the tables of means, each seed's own ratio of the
loop to the better `mi.render` image, so one lucky or unlucky run shows (bench/as_written.py)."""
from __future__ import annotations

from pathlib import Path

import pytest

from bench.as_written import METHODS, METRICS, PARTS, SceneResult, spread_section
from bench.dev_references import DevScene


def result(name: str, per_method: dict[str, list[float]]) -> SceneResult:
    """A scene whose every metric has the same per-seed values for each method."""
    values = {m: {k: list(per_method.get(m, [1.0, 1.0])) for k in METRICS} for m in METHODS + PARTS}
    return SceneResult(DevScene(name, Path(name), 1), "scenes/dev", "gaussian", "8×8", 64, values)


def test_each_seed_divides_the_loop_by_that_seeds_image_of_the_better_method_on_the_mean() -> None:
    # OIDN better on the mean (1.5 vs 2.0), raw better on seed 1: seed 1 still divides by OIDN's
    scene = result("a", {"mitsuba_raw": [3.0, 1.0], "mitsuba_oidn": [1.0, 2.0], "loop": [0.9, 2.2]})
    assert scene.better_mitsuba("smape") == "mitsuba_oidn"
    assert scene.seed_ratios("smape") == pytest.approx([0.9, 1.1])
    assert scene.ratio("smape") == pytest.approx(3.1 / 3.0)
    assert not scene.wins_every_seed


def test_the_spread_section_counts_the_scenes_ahead_on_every_seed_and_lists_each_seed() -> None:
    steady = result("steady", {"loop": [0.5, 0.6]})
    lucky = result("lucky", {"loop": [0.8, 1.1]})  # ahead on the mean, behind on seed 1
    text = spread_section([steady, lucky], [0, 1])
    assert "on **1 of 2** scenes" in text
    assert "| scenes/dev steady (gaussian) | 0.50 0.60 | 0.50 0.60 |" in text
    assert "| scenes/dev lucky (gaussian) | 0.80 1.10 | 0.80 1.10 |" in text


def test_one_seed_has_no_spread_section() -> None:
    assert spread_section([result("a", {"loop": [0.5]})], [0]) == ""
