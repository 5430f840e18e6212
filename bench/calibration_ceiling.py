"""The repeatable-error ceiling of the calibration report's per-pixel Spearman.

One render's true SMAPE map is the scene's repeatable error (where the denoiser struggles) plus
that render's own leftover noise, which changes with the seed and which no predictor of the
expected error can rank. Per scene, K renders that differ only in their seed, each the
calibration loop's first iteration (same spec, same networks, `max_iterations=1`); the ceiling is
the Spearman of the mean of K − 1 true maps against the K-th, averaged over the K leave-one-out
choices: what a predictor that knew the expected error (estimated from K − 1 renders, so a little
low) scores against one render. The network's Spearman is measured on the same K renders, against
each render's own true map, as the report's per-iteration figure is. Measured first by the
removed bench/experiments/error_ceiling.py (docs/decisions.md, "How much of a pixel's error can be
predicted").
"""
from __future__ import annotations

import math
import statistics
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from bench.quality_measures import spearman

# The goal: the error network's per-pixel Spearman ≥ 90 % of the repeatable ceiling, what a
# perfect predictor of the expected error scores (a fixed 0.7 ignored how much noise a scene has)
CEILING_GOAL = 0.90
CEILING_RENDERS = 8  # K: the figure in docs/decisions.md came from 8 renders per scene
CEILING_RENDER_RANGE = (4, 8)
# Away from the report's loop seeds (0, 1, …): the ceiling's renders are new ones.
CEILING_FIRST_SEED = 1000


@dataclass(frozen=True)
class FirstIterationMaps:
    """One render's (H, W) maps at the report's first spp."""

    true: np.ndarray
    predicted: np.ndarray


@dataclass(frozen=True)
class CeilingScore:
    """One scene: the repeatable ceiling and the network's Spearman on the same K renders."""

    spp: float
    renders: int
    ceiling: float            # mean over k of Spearman(mean of the other K − 1 true maps, true map k)
    network: float            # mean over k of Spearman(predicted map k, true map k)
    network_min: float = math.nan
    network_max: float = math.nan

    @property
    def ratio(self) -> float:
        return self.network / self.ceiling if self.ceiling > 0 else math.nan


def leave_one_out_spearman(true_maps: np.ndarray) -> float:
    """(K, H, W) true error maps of one scene → mean over k of Spearman(mean of the others, map k)."""
    k = len(true_maps)
    if k < 2:
        raise ValueError("leave-one-out needs at least two maps")
    total = true_maps.sum(axis=0)
    return float(np.mean([spearman((total - m) / (k - 1), m) for m in true_maps]))


def ceiling_score(spp: float, maps: list[FirstIterationMaps]) -> CeilingScore:
    network = [spearman(m.predicted, m.true) for m in maps]
    return CeilingScore(spp, len(maps), leave_one_out_spearman(np.stack([m.true for m in maps])),
                        float(np.mean(network)), float(np.min(network)), float(np.max(network)))


def scene_ceiling(render: Callable[[int], tuple[float, FirstIterationMaps]], renders: int) -> CeilingScore:
    """`render(seed)` → (spp, maps) of one first iteration; K = `renders` seeds from CEILING_FIRST_SEED."""
    if not CEILING_RENDER_RANGE[0] <= renders <= CEILING_RENDER_RANGE[1]:
        raise ValueError(f"the ceiling takes {CEILING_RENDER_RANGE[0]}–{CEILING_RENDER_RANGE[1]} renders per scene, "
                         f"got {renders}")
    runs = [render(CEILING_FIRST_SEED + k) for k in range(renders)]
    return ceiling_score(runs[0][0], [maps for _, maps in runs])


@dataclass(frozen=True)
class CeilingMedian:
    ceiling: float
    network: float

    @property
    def ratio(self) -> float:
        """The goal's figure: the median scene's network Spearman over the median scene's ceiling."""
        return self.network / self.ceiling if self.ceiling > 0 else math.nan


def ceiling_median(scores: dict[str, CeilingScore]) -> CeilingMedian:
    return CeilingMedian(statistics.median(s.ceiling for s in scores.values()),
                         statistics.median(s.network for s in scores.values()))


def ceiling_bound_line(scores: dict[str, CeilingScore]) -> str:
    """The bound as one sentence for the report's header."""
    median = ceiling_median(scores)
    spp = next(iter(scores.values())).spp
    renders = next(iter(scores.values())).renders
    verdict = "met" if median.ratio >= CEILING_GOAL else "not met"
    return (f"**Bound: the error network's per-pixel Spearman ≥ {CEILING_GOAL:.0%} of the repeatable ceiling** "
            f"At {spp:g} spp, over {renders} renders per scene: median network "
            f"{median.network:.2f} / median ceiling {median.ceiling:.2f} = **{median.ratio:.0%}** ({verdict}).")


def ceiling_table(scores: dict[str, CeilingScore]) -> str:
    lines = ["| scene | repeatable ceiling | network (mean of the renders; min–max) | network / ceiling |",
             "|---|---:|---:|---:|"]
    for name, s in scores.items():
        lines.append(f"| {name} | {s.ceiling:.2f} | {s.network:.2f} ({s.network_min:.2f}–{s.network_max:.2f}) | "
                     f"{_percent(s.ratio)} |")
    median = ceiling_median(scores)
    lines.append(f"| **median** | **{median.ceiling:.2f}** | **{median.network:.2f}** | **{_percent(median.ratio)}** |")
    return "\n".join(lines)


def _percent(ratio: float) -> str:
    return f"{ratio:.0%}" if math.isfinite(ratio) else "n/a (ceiling ≤ 0)"
