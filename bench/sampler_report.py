"""Renderer throughput vs `mi.render` at equal samples, and the memory of one large pass.

Every case renders the same scene both ways, interleaved, so load on the shared machine hits
both alike; the figure quoted is the median of the per-run ratios.
"""
from __future__ import annotations

import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from bench.common import provenance
from service.render.framebuffer import FrameBuffer
from service.render.renderer import render_samples
from service.render.runtime import active_variant, mitsuba
from service.render.scenes import load_scene


def bench_sampler(size: int, spp: int, repeats: int) -> dict:
    """Interleaved runs of mi.render and render_samples on the Cornell box at equal samples."""
    mi = mitsuba()
    scene = load_scene("cornell-box", width=size, height=size)
    counts = np.full((size, size), spp)
    # One untimed run of each first: kernels are compiled (and cached) on first use.
    np.asarray(mi.render(scene, spp=spp))
    render_samples(scene, counts, FrameBuffer.empty(size, size))
    ours, theirs = [], []
    for rep in range(repeats):
        t0 = time.perf_counter()
        np.asarray(mi.render(scene, spp=spp, seed=rep))
        theirs.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        render_samples(scene, counts, FrameBuffer.empty(size, size), seed=rep)
        ours.append(time.perf_counter() - t0)
    samples = size * size * spp
    ratios = [t / o for t, o in zip(theirs, ours)]
    return {"variant": active_variant(), "size": size, "spp": spp, "samples": samples,
            "mi_render_s": float(np.median(theirs)), "ours_s": float(np.median(ours)),
            "mi_render_msps": samples / np.median(theirs) / 1e6, "ours_msps": samples / np.median(ours) / 1e6,
            "ratio": float(np.median(ratios)), "ratios": ratios}


def write_sampler_report(result: dict, out: Path) -> Path:
    path = out / "sampler.md"
    out.mkdir(parents=True, exist_ok=True)
    path.write_text(f"""# Renderer throughput vs `mi.render`

{provenance(variant=result['variant'])}

Cornell box {result['size']}², {result['spp']} spp ({result['samples']:,} samples), runs interleaved,
median of {len(result['ratios'])}. Ours includes the first-hit AOVs (albedo, normal, depth) that
`mi.render` does not compute, and accumulates sum and sum of squares per pixel.

| renderer | seconds | M samples/s |
|---|---:|---:|
| `mi.render` | {result['mi_render_s']:.2f} | {result['mi_render_msps']:.2f} |
| `render_samples` (per-pixel counts) | {result['ours_s']:.2f} | {result['ours_msps']:.2f} |

Throughput ratio ours / `mi.render`: **{result['ratio']:.2f}×** (per run: {', '.join(f'{r:.2f}' for r in result['ratios'])}; target ≥ 0.9×).
""")
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


def bench_memory(size: int = 1024, spp: int = 64) -> dict:
    out = subprocess.run([sys.executable, "-c", MEMORY_PROBE, str(size), str(spp)],
                         capture_output=True, text=True, check=True).stdout.split()
    peak_kb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss  # Linux reports KiB
    return {"size": size, "spp": spp, "samples": int(out[0]), "chunks": int(out[1]), "seconds": float(out[2]),
            "peak_rss_gb": peak_kb / 2**20}


def write_memory_report(result: dict, out: Path) -> Path:
    path = out / "memory.md"
    out.mkdir(parents=True, exist_ok=True)
    path.write_text(f"""# Memory of one large render pass

{provenance()}

Cornell box {result['size']}² × {result['spp']} spp = {result['samples']:,} samples in {result['chunks']} chunks
of at most 2²² lanes, rendered by `render_samples` in a fresh process: **peak RSS
{result['peak_rss_gb']:.2f} GB** (whole process: Python, Mitsuba, the frame buffer), {result['seconds']:.1f} s.
""")
    return path
