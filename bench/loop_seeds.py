"""The loop benchmark's allocation bound over seeds: the product (d)'s SMAPE at
equal samples against the true-error allocation (o), both ÷ uniform + KPCN (b), per scene and for
the median scene, each as its mean ± sample standard deviation over the loop seeds (min–max).

The goal: the loop within GOAL_GAP_TO_BOUND of (o) on the median scene, that is, the median over
the scenes of (d)/(b) − (o)/(b) at most 0.02. (o) allocates by the reference's true error map, so
the gap is what a better error network could still buy with this allocator — and also what it could
not: (o) knows where this render's noise landed. (x) allocates by the expected true error
(bench.loop_expected_bound); where it ran, the gap to it is reported beside.
"""
from __future__ import annotations

import math
import statistics
from collections.abc import Callable
from dataclasses import dataclass

from bench.loop_run import Headline

GOAL_GAP_TO_BOUND = 0.02  # (d)/(b) within 0.02 of (o)/(b) on the median scene: the network costs ≤ 2 % SMAPE


@dataclass(frozen=True)
class Spread:
    """One figure over the seeds."""

    mean: float
    sd: float  # sample standard deviation (n − 1); nan for one seed
    low: float
    high: float

    def text(self, digits: int = 3) -> str:
        sd = f" ± {self.sd:.{digits}f}" if math.isfinite(self.sd) else ""
        return f"{self.mean:.{digits}f}{sd} ({self.low:.{digits}f}–{self.high:.{digits}f})"


def spread(values: list[float]) -> Spread:
    if not values:
        return Spread(math.nan, math.nan, math.nan, math.nan)
    sd = statistics.stdev(values) if len(values) > 1 else math.nan
    return Spread(statistics.mean(values), sd, min(values), max(values))


def gaps(head: Headline) -> dict[str, float]:
    """Per scene: SMAPE (d)/(b) − (o)/(b) at equal samples; scenes without (o) are left out."""
    return {scene: ratio - head.oracle_ratio[scene] for scene, ratio in head.smape_ratio.items()
            if scene in head.oracle_ratio}


def expected_gaps(head: Headline) -> dict[str, float]:
    """Per scene: SMAPE (d)/(b) − (x)/(b), the gap to the expected-error allocation
    (bench.loop_expected_bound); scenes without (x) are left out."""
    return {scene: ratio - head.expected_ratio[scene] for scene, ratio in head.smape_ratio.items()
            if scene in head.expected_ratio}


# The table's columns: (header, a seed's per-scene figures); the (x) ones only where (x) ran.
COLUMNS: tuple[tuple[str, Callable[[Headline], dict[str, float]]], ...] = (
    ("SMAPE (d)/(b)", lambda head: head.smape_ratio),
    ("SMAPE (o)/(b)", lambda head: head.oracle_ratio),
    ("gap (d)/(b) − (o)/(b)", gaps),
    ("SMAPE (x)/(b)", lambda head: head.expected_ratio),
    ("gap (d)/(b) − (x)/(b)", expected_gaps),
)


def per_scene(heads: dict[int, Headline], figures: Callable[[Headline], dict[str, float]], scene: str) -> Spread:
    return spread([figures(head)[scene] for head in heads.values() if scene in figures(head)])


def median_scene(heads: dict[int, Headline], figures: Callable[[Headline], dict[str, float]]) -> Spread:
    """Per seed the median over the scenes, then its spread over the seeds."""
    return spread([statistics.median(figures(head).values()) for head in heads.values() if figures(head)])


def seed_table(heads: dict[int, Headline]) -> str:
    scenes = list(next(iter(heads.values())).smape_ratio)
    columns = [(header, f) for header, f in COLUMNS if any(f(head) for head in heads.values())]
    lines = ["| scene | " + " | ".join(header for header, _ in columns) + " |", "|---|" + "---:|" * len(columns)]
    for scene in scenes:
        lines.append(f"| {scene} | " + " | ".join(per_scene(heads, f, scene).text() for _, f in columns) + " |")
    lines.append("| **median** | " + " | ".join(f"**{median_scene(heads, f).text()}**" for _, f in columns) + " |")
    return "\n".join(lines)


def bound_line(heads: dict[int, Headline]) -> str:
    """The allocation bound as one sentence for the report's header."""
    gap = median_scene(heads, gaps)
    if not math.isfinite(gap.mean):
        return "Bound: the true-error allocation (o) or uniform + KPCN (b) was not run: no gap to state."
    seeds = ", ".join(str(seed) for seed in heads)
    verdict = "met" if gap.mean <= GOAL_GAP_TO_BOUND else "not met"
    line = (f"**Bound: the loop's SMAPE at equal samples within {GOAL_GAP_TO_BOUND} of the true-error allocation "
            f"(o) on the median scene**. Median over the scenes of (d)/(b) − (o)/(b): "
            f"**{gap.text()}** (mean ± s.d. over seeds {seeds}, min–max in brackets; {verdict}); median (d)/(b) "
            f"{median_scene(heads, COLUMNS[0][1]).text()}, median (o)/(b) {median_scene(heads, COLUMNS[1][1]).text()}.")
    expected = median_scene(heads, expected_gaps)
    if not math.isfinite(expected.mean):
        return line
    return (line + f" Against the allocation by the expected true error (x), what a perfect predictor of the scene's "
            f"error reaches without knowing this render's noise: median (x)/(b) "
            f"{median_scene(heads, COLUMNS[3][1]).text()}, median gap (d)/(b) − (x)/(b) **{expected.text()}** "
            f"({'within' if expected.mean <= GOAL_GAP_TO_BOUND else 'above'} {GOAL_GAP_TO_BOUND}).")
