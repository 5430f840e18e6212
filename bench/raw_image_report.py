"""The raw image (`renderloop render --no-denoise`) against `mi.render`'s at equal samples, and
what splatting it costs (docs/sampler.md, beside the throughput table).

Quality: per filter, one scene as written (the case's built-in scene with that film filter and
the independent sampler, as sampler_report.case_scene builds it), rendered uniformly at each
spp by our renderer (`FrameBuffer.raw`: one uniform pass, what `--spp N --no-denoise` writes)
and by `mi.render`, several seeds each, scored by per-pixel relMSE against a high-spp
`mi.render` reference of the same scene. The ratio of the mean relMSEs carries the seeds'
noise: its standard error (the delta method on two independent means) says whether a row
resolves the 5 % bar. The seeds are sized for a standard error of ~1.5 % at 128²: a seed's
relMSE varies by ~2 % (box, tent, Gaussian) and 4–5 % (Mitchell, whose negative lobes splat
bright samples into dark pixels) between seeds, for ours and `mi.render`'s alike.
Cost: the same pass with and without the splat sums (render_samples(splat=False)),
interleaved, median of the repeats.
"""
from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from bench.sampler_report import SamplerCase, case_scene
from models.metrics import relmse
from service.loop.tensors import nchw
from service.render.framebuffer import FrameBuffer
from service.render.renderer import render_samples
from service.render.runtime import mitsuba

QUALITY_FILTERS = ("box", "tent", "gaussian", "mitchell")
QUALITY_SPP = (16, 64, 128)
QUALITY_SIZE = 128
# Seeds per filter for a ratio standard error ≲ 1.5 % (module docstring): √(2·cv²/n) with a
# seed's cv ~2 % needs ≥ 4 seeds, with Mitchell's 4–5 % ≥ 18 (measured at 128²: 8 seeds per
# row, 24 more at 128 spp; 16 Mitchell seeds left standard errors of 1.4–1.7 %).
QUALITY_SEEDS: Mapping[str, int] = {"box": 6, "tent": 6, "gaussian": 6, "mitchell": 24}
# The reference's own noise adds spp / REFERENCE_SPP of `mi.render`'s relMSE to both sides
# (6 % at 128 spp), which pulls every ratio towards 1 by that share.
REFERENCE_SPP = 2048
TARGET_QUALITY_RATIO = 1.05  # our raw relMSE ÷ mi.render's the raw image is held to
SIGNIFICANT = 2.0  # standard errors a ratio must clear the target by to count as above it
COST_FILTERS = ("tent", "gaussian", "mitchell")
# (film side, spps): a small film at several rates and a larger one at the loop's first rate,
# where the splat's film-sized sums no longer sit in cache.
COST_CASES = ((128, (16, 64, 128)), (512, (16,)))


def ratio_of_means(ours: tuple[float, ...], theirs: tuple[float, ...]) -> tuple[float, float]:
    """mean(ours) ÷ mean(theirs) and its standard error from the two samples' spreads (the
    delta method for a ratio of independent means: relative variances add)."""
    a, b = np.asarray(ours, dtype=np.float64), np.asarray(theirs, dtype=np.float64)
    ratio = float(a.mean() / b.mean())
    if len(a) < 2 or len(b) < 2:
        return ratio, math.nan
    relative = a.var(ddof=1) / (len(a) * a.mean() ** 2) + b.var(ddof=1) / (len(b) * b.mean() ** 2)
    return ratio, ratio * math.sqrt(relative)


@dataclass(frozen=True)
class QualityRow:
    filter: str
    spp: int
    ours: tuple[float, ...]  # relMSE per seed of our raw image
    fis: tuple[float, ...]  # relMSE per seed of the per-pixel (FIS) estimate the denoisers read
    theirs: tuple[float, ...]  # relMSE per seed of mi.render's

    @property
    def ratio(self) -> float:
        return ratio_of_means(self.ours, self.theirs)[0]

    @property
    def ratio_se(self) -> float:
        return ratio_of_means(self.ours, self.theirs)[1]

    @property
    def fis_ratio(self) -> float:
        return float(np.mean(self.fis) / np.mean(self.theirs))

    @property
    def verdict(self) -> str:
        """'within' the target, 'above' it by more than SIGNIFICANT standard errors, or above
        it by less ('within noise'): the seeds cannot tell that row from the target."""
        if self.ratio <= TARGET_QUALITY_RATIO:
            return "within"
        return "above" if self.ratio - SIGNIFICANT * self.ratio_se > TARGET_QUALITY_RATIO else "within noise"


def _relmse(image: np.ndarray, reference: np.ndarray) -> float:
    return float(relmse(nchw(np.ascontiguousarray(image[..., :3])), nchw(reference)))


def splatted(buffer: FrameBuffer) -> np.ndarray:
    """The raw image a uniform `--spp N --no-denoise` pass writes."""
    return buffer.raw


def quality_rows(case_for=lambda f: SamplerCase("cornell-box", "path", f), size: int = QUALITY_SIZE,
                 spps: tuple[int, ...] = QUALITY_SPP, seeds: Mapping[str, int] = QUALITY_SEEDS,
                 reference_spp: int = REFERENCE_SPP,
                 raw_of: Callable[[FrameBuffer], np.ndarray] = splatted) -> list[QualityRow]:
    """One row per filter in `seeds` (in QUALITY_FILTERS order) and spp. `raw_of`: what is
    scored as our raw image (tests plant a wrong one to see the table catch it)."""
    mi = mitsuba()
    rows = []
    for filter_type in (f for f in QUALITY_FILTERS if f in seeds):
        scene = case_scene(case_for(filter_type), size)
        reference = np.asarray(mi.render(scene, spp=reference_spp, seed=0x5EED))[..., :3]
        for spp in spps:
            ours, fis, theirs = [], [], []
            for seed in range(seeds[filter_type]):
                buffer = FrameBuffer.empty(size, size)
                render_samples(scene, np.full((size, size), spp), buffer, seed=seed)
                ours.append(_relmse(raw_of(buffer), reference))
                fis.append(_relmse(buffer.mean, reference))
                theirs.append(_relmse(np.asarray(mi.render(scene, spp=spp, seed=1000 + seed)), reference))
            rows.append(QualityRow(filter_type, spp, tuple(ours), tuple(fis), tuple(theirs)))
    return rows


def quality_table(rows: list[QualityRow]) -> str:
    lines = ["| filter | spp | seeds | ours raw relMSE | `mi.render` relMSE | **ratio ± SE** | vs the bar "
             "| per-pixel (FIS) relMSE | FIS ratio |",
             "|---|---:|---:|---:|---:|---:|---|---:|---:|"]
    for r in rows:
        lines.append(f"| {r.filter} | {r.spp} | {len(r.ours)} | {np.mean(r.ours):.5f} | {np.mean(r.theirs):.5f} | "
                     f"**{r.ratio:.3f} ± {r.ratio_se:.3f}×** | {r.verdict} | {np.mean(r.fis):.5f} | {r.fis_ratio:.2f}× |")
    return "\n".join(lines)


def seeds_text(seeds: Mapping[str, int] = QUALITY_SEEDS) -> str:
    """'8 seeds (box, tent, gaussian) and 16 (mitchell)': the report's sentence on the seeds."""
    groups: dict[int, list[str]] = {}
    for name, count in seeds.items():
        groups.setdefault(count, []).append(name)
    parts = [f"{count} ({', '.join(names)})" for count, names in groups.items()]
    return f"{parts[0].replace(' (', ' seeds (', 1)}" + "".join(f" and {p}" for p in parts[1:])


@dataclass(frozen=True)
class CostRow:
    filter: str
    size: int
    spp: int
    with_splat_s: float  # median seconds of one pass
    without_splat_s: float
    samples: int

    @property
    def ns_per_sample(self) -> tuple[float, float]:
        return self.with_splat_s / self.samples * 1e9, self.without_splat_s / self.samples * 1e9

    @property
    def overhead(self) -> float:
        return self.with_splat_s / self.without_splat_s - 1.0


def cost_rows(case_for=lambda f: SamplerCase("cornell-box", "path", f), cases=COST_CASES,
              repeats: int = 3) -> list[CostRow]:
    rows = []
    for size, spps in cases:
        for filter_type in COST_FILTERS:
            rows += _cost_rows(case_scene(case_for(filter_type), size), filter_type, size, spps, repeats)
    return rows


def _cost_rows(scene, filter_type: str, size: int, spps: tuple[int, ...], repeats: int) -> list[CostRow]:
    """One filter's scene at one film size: each spp's pass with and without the splat sums."""
    rows = []
    for spp in spps:
        counts = np.full((size, size), spp)
        for splat in (True, False):  # kernels are compiled (and cached) on first use
            render_samples(scene, counts, FrameBuffer.empty(size, size), splat=splat)
        with_splat, without = [], []
        for rep in range(repeats):
            for splat, times in ((True, with_splat), (False, without)):
                t0 = time.perf_counter()
                render_samples(scene, counts, FrameBuffer.empty(size, size), seed=rep, splat=splat)
                times.append(time.perf_counter() - t0)
        rows.append(CostRow(filter_type, size, spp, statistics.median(with_splat), statistics.median(without),
                            size * size * spp))
    return rows


def cost_table(rows: list[CostRow]) -> str:
    lines = ["| film | filter | spp | with splat s | without s | ns/sample with | ns/sample without | splat cost |",
             "|---|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        with_ns, without_ns = r.ns_per_sample
        lines.append(f"| {r.size}² | {r.filter} | {r.spp} | {r.with_splat_s:.3f} | {r.without_splat_s:.3f} | {with_ns:.0f} | "
                     f"{without_ns:.0f} | {100 * r.overhead:+.0f} % |")
    return "\n".join(lines)


def report_fields(quality: list[QualityRow], cost: list[CostRow], quality_seconds: float = math.nan) -> dict[str, object]:
    """The raw-image sections of docs/sampler.md (bench/templates/sampler.md)."""
    share = max(QUALITY_SPP) / REFERENCE_SPP  # the reference's noise beside mi.render's at the top spp
    return {"quality_size": QUALITY_SIZE, "quality_seeds": seeds_text(), "reference_spp": REFERENCE_SPP,
            "reference_share": f"{100 * share:.0f}", "bar_reads": f"{(TARGET_QUALITY_RATIO + share) / (1 + share):.3f}",
            "quality_target": f"{TARGET_QUALITY_RATIO:g}", "significant": f"{SIGNIFICANT:g}",
            "quality_table": quality_table(quality), "quality_minutes": f"{quality_seconds / 60:.1f}",
            "cost_sizes": " and ".join(f"{size}²" for size, _ in COST_CASES), "cost_table": cost_table(cost)}
