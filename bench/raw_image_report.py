"""The raw image (`renderloop render --no-denoise`) against `mi.render`'s at equal samples, and
what splatting it costs (docs/sampler.md, beside the throughput table).

Quality: per filter, one scene as written (the case's built-in scene with that film filter and
the independent sampler, as sampler_report.case_scene builds it), rendered uniformly at each
spp by our renderer (`FrameBuffer.raw`: one uniform pass, what `--spp N --no-denoise` writes)
and by `mi.render`, a few seeds each, scored by per-pixel relMSE against a high-spp `mi.render`
reference of the same scene. Cost: the same pass with and without the splat sums
(render_samples(splat=False)), interleaved, median of the repeats.
"""
from __future__ import annotations

import statistics
import time
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
QUALITY_SIZE = 64
QUALITY_SEEDS = 3
REFERENCE_SPP = 4096
TARGET_QUALITY_RATIO = 1.05  # our raw relMSE ÷ mi.render's the raw image is held to
COST_FILTERS = ("tent", "gaussian", "mitchell")
# (film side, spps): a small film at several rates and a larger one at the loop's first rate,
# where the splat's film-sized sums no longer sit in cache.
COST_CASES = ((128, (16, 64, 128)), (512, (16,)))


@dataclass(frozen=True)
class QualityRow:
    filter: str
    spp: int
    ours: tuple[float, ...]  # relMSE per seed of our raw image
    fis: tuple[float, ...]  # relMSE per seed of the per-pixel (FIS) estimate the denoisers read
    theirs: tuple[float, ...]  # relMSE per seed of mi.render's

    @property
    def ratio(self) -> float:
        return float(np.mean(self.ours) / np.mean(self.theirs))

    @property
    def fis_ratio(self) -> float:
        return float(np.mean(self.fis) / np.mean(self.theirs))


def _relmse(image: np.ndarray, reference: np.ndarray) -> float:
    return float(relmse(nchw(np.ascontiguousarray(image[..., :3])), nchw(reference)))


def quality_rows(case_for=lambda f: SamplerCase("cornell-box", "path", f), size: int = QUALITY_SIZE,
                 spps: tuple[int, ...] = QUALITY_SPP, seeds: int = QUALITY_SEEDS) -> list[QualityRow]:
    mi = mitsuba()
    rows = []
    for filter_type in QUALITY_FILTERS:
        scene = case_scene(case_for(filter_type), size)
        reference = np.asarray(mi.render(scene, spp=REFERENCE_SPP, seed=0x5EED))[..., :3]
        for spp in spps:
            ours, fis, theirs = [], [], []
            for seed in range(seeds):
                buffer = FrameBuffer.empty(size, size)
                render_samples(scene, np.full((size, size), spp), buffer, seed=seed)
                ours.append(_relmse(buffer.raw, reference))
                fis.append(_relmse(buffer.mean, reference))
                theirs.append(_relmse(np.asarray(mi.render(scene, spp=spp, seed=1000 + seed)), reference))
            rows.append(QualityRow(filter_type, spp, tuple(ours), tuple(fis), tuple(theirs)))
    return rows


def quality_table(rows: list[QualityRow]) -> str:
    lines = ["| filter | spp | ours raw relMSE | `mi.render` relMSE | **ratio** | per-pixel (FIS) relMSE | FIS ratio |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r.filter} | {r.spp} | {np.mean(r.ours):.5f} | {np.mean(r.theirs):.5f} | "
                     f"**{r.ratio:.3f}×** | {np.mean(r.fis):.5f} | {r.fis_ratio:.2f}× |")
    return "\n".join(lines)


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


def report_fields(quality: list[QualityRow], cost: list[CostRow]) -> dict[str, object]:
    """The raw-image sections of docs/sampler.md (bench/templates/sampler.md)."""
    return {"quality_size": QUALITY_SIZE, "quality_seeds": QUALITY_SEEDS, "reference_spp": REFERENCE_SPP,
            "quality_target": f"{TARGET_QUALITY_RATIO:g}", "quality_table": quality_table(quality),
            "cost_sizes": " and ".join(f"{size}²" for size, _ in COST_CASES), "cost_table": cost_table(cost)}
