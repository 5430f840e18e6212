"""Renderer throughput vs `mi.render` at equal samples (docs/sampler.md), and the memory of one
large render pass (docs/memory.md).

The throughput comparison runs a list of cases, each a (scene, integrator, reconstruction
filter): a case fixes everything both renderers see, so adding a filter or an integrator is
one more `SamplerCase` line. Every case renders the same scene both ways, interleaved, so load
on the shared machine hits both alike; the figure quoted is the median of the per-run ratios.
"""
from __future__ import annotations

import resource
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench.common import fill, provenance
from service.render.builtin import BUILTIN_BY_NAME
from service.render.framebuffer import FrameBuffer
from service.render.renderer import DEFAULT_MAX_WAVEFRONT, render_samples
from service.render.runtime import active_variant, mitsuba

TARGET_RATIO = 0.9  # ours / mi.render throughput the renderer is held to


@dataclass(frozen=True)
class SamplerCase:
    scene: str  # a built-in scene name
    integrator: str  # a Mitsuba integrator plugin
    filter: str  # a Mitsuba reconstruction filter plugin (the film's rfilter)
    max_depth: int | None = 8  # None for integrators without one (direct)

    @property
    def label(self) -> str:
        return f"{self.scene} / {self.integrator} / {self.filter}"


# Each integrator with the box filter and with a filter whose offsets are importance-sampled
# (tent, gaussian): the renderer's cost of filtering shows up beside mi.render's splatting.
CASES: tuple[SamplerCase, ...] = (
    SamplerCase("cornell-box", "path", "box"),
    SamplerCase("cornell-box", "path", "gaussian"),
    SamplerCase("cornell-box", "direct", "box", max_depth=None),
    SamplerCase("cornell-box", "direct", "tent", max_depth=None),
    SamplerCase("veiled", "volpath", "box"),
    SamplerCase("veiled", "volpath", "gaussian"),
)


@dataclass(frozen=True)
class SamplerResult:
    case: SamplerCase
    size: int
    spp: int
    mi_render_s: float  # median seconds
    ours_s: float
    ratios: tuple[float, ...]  # per interleaved run: mi.render seconds / ours

    @property
    def samples(self) -> int:
        return self.size * self.size * self.spp

    @property
    def mi_render_msps(self) -> float:
        return self.samples / self.mi_render_s / 1e6

    @property
    def ours_msps(self) -> float:
        return self.samples / self.ours_s / 1e6

    @property
    def ratio(self) -> float:
        return statistics.median(self.ratios)


def case_scene(case: SamplerCase, size: int):
    """The case's scene: the built-in description with the case's integrator, filter and film
    size, and the independent sampler (what the renderer uses for per-pixel counts)."""
    mi = mitsuba()
    description = BUILTIN_BY_NAME[case.scene].build(0)
    integrator = {"type": case.integrator}
    if case.max_depth is not None:
        integrator["max_depth"] = case.max_depth
    description["integrator"] = integrator
    sensor = description["sensor"]
    film = dict(sensor.get("film", {"type": "hdrfilm"}))
    film.update(width=size, height=size, rfilter={"type": case.filter})
    sensor["film"] = film
    sensor["sampler"] = {"type": "independent"}
    return mi.load_dict(description)


def bench_case(case: SamplerCase, size: int, spp: int, repeats: int) -> SamplerResult:
    """Interleaved runs of mi.render and render_samples on one case at equal samples."""
    mi = mitsuba()
    scene = case_scene(case, size)
    integrator = scene.integrator()
    counts = np.full((size, size), spp)
    # One untimed run of each first: kernels are compiled (and cached) on first use.
    np.asarray(mi.render(scene, spp=spp, integrator=integrator))
    render_samples(scene, counts, FrameBuffer.empty(size, size), integrator=integrator)
    ours, theirs = [], []
    for rep in range(repeats):
        t0 = time.perf_counter()
        np.asarray(mi.render(scene, spp=spp, seed=rep, integrator=integrator))
        theirs.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        render_samples(scene, counts, FrameBuffer.empty(size, size), integrator=integrator, seed=rep)
        ours.append(time.perf_counter() - t0)
    return SamplerResult(case, size, spp, statistics.median(theirs), statistics.median(ours),
                         tuple(t / o for t, o in zip(theirs, ours)))


def bench_sampler(size: int, spp: int, repeats: int, cases: tuple[SamplerCase, ...] = CASES) -> list[SamplerResult]:
    return [bench_case(case, size, spp, repeats) for case in cases]


def sampler_table(results: list[SamplerResult]) -> str:
    """The markdown table both the sampler report and the loop report show."""
    lines = ["| scene / integrator / filter | `mi.render` s | ours s | `mi.render` M samples/s | ours M samples/s "
             "| ratio ours / `mi.render` (per run) |",
             "|---|---:|---:|---:|---:|---|"]
    for r in results:
        runs = ", ".join(f"{x:.2f}" for x in r.ratios)
        lines.append(f"| {r.case.label} | {r.mi_render_s:.3f} | {r.ours_s:.3f} | {r.mi_render_msps:.2f} | "
                     f"{r.ours_msps:.2f} | **{r.ratio:.2f}×** ({runs}) |")
    return "\n".join(lines)


def write_sampler_report(results: list[SamplerResult], out: Path, raw: dict[str, object]) -> Path:
    """`raw`: the raw-image and stratified-pass sections' fields (bench.raw_image_report.report_fields,
    bench.stratified_pass_report.report_fields)."""
    first = results[0]
    path = out / "sampler.md"
    out.mkdir(parents=True, exist_ok=True)
    path.write_text(fill("sampler.md", provenance=provenance(variant=active_variant()), size=first.size,
                         spp=first.spp, samples=f"{first.samples:,}", repeats=len(first.ratios),
                         table=sampler_table(results), target=f"{TARGET_RATIO:g}", **raw))
    return path


# Run in a child process so its peak RSS is the render pass's alone (ru_maxrss of children).
MEMORY_PROBE = """
import numpy as np, sys
from service.render.framebuffer import FrameBuffer
from service.render.renderer import render_samples
from service.render.scenes import load_scene
size, spp = int(sys.argv[1]), int(sys.argv[2])
scene = load_scene("cornell-box", width=size, height=size)
result = render_samples(scene, np.full((size, size), spp), FrameBuffer.empty(size, size))
print(result.samples, result.chunks, f"{result.seconds:.1f}")
"""


@dataclass(frozen=True)
class MemoryResult:
    size: int
    spp: int
    samples: int
    chunks: int
    seconds: float
    peak_rss_gb: float


def bench_memory(size: int = 1024, spp: int = 64) -> MemoryResult:
    out = subprocess.run([sys.executable, "-c", MEMORY_PROBE, str(size), str(spp)],
                         capture_output=True, text=True, check=True).stdout.split()
    peak_kb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss  # Linux reports KiB
    return MemoryResult(size, spp, int(out[0]), int(out[1]), float(out[2]), peak_kb / 2**20)


def write_memory_report(result: MemoryResult, out: Path) -> Path:
    path = out / "memory.md"
    out.mkdir(parents=True, exist_ok=True)
    lanes = int(np.log2(DEFAULT_MAX_WAVEFRONT))
    path.write_text(fill("memory.md", provenance=provenance(variant=active_variant()), size=result.size,
                         spp=result.spp, samples=f"{result.samples:,}", chunks=result.chunks, lanes=lanes,
                         peak_rss_gb=f"{result.peak_rss_gb:.2f}", seconds=f"{result.seconds:.1f}"))
    return path
