"""What does one sample cost where it lands? (docs/error-network.md, "Allocation: what a sample costs where it lands")

At equal samples the error-adaptive loop (d) renders longer than uniform (b) on some scenes
(docs/benchmarks-dev.md: point_object 0.78 s against 0.40 s over four iterations): its samples
leave pixels whose every sample agreed — mostly camera rays that miss everything — for
surfaces, where a sample traces a whole path. Per scene, after a uniform pass that finds which
pixels any camera ray hits, the same number of samples is rendered three ways — spread uniformly,
spread over the hit pixels only, over the missed pixels only — each timed as the fastest of
`--repeats` identical passes (Dr.Jit's kernels are compiled by the first).

    python -m bench.experiments.sample_cost [--suite dev] [--spp 32] [--repeats 2] [--only SCENE …]
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from bench.dev_references import SUITES, dev_scenes
from service.loop.loop import RenderLoop
from service.loop.spec import LoopSpec
from service.render.framebuffer import FrameBuffer
from service.render.renderer import render_samples


def spread_over(mask: np.ndarray, total: int) -> np.ndarray:
    """Integer counts summing to exactly `total`, as even as possible over the True pixels of
    `mask` (the first pixels in raster order take the remainder), 0 elsewhere."""
    counts = np.zeros(mask.shape, np.int64)
    where = np.flatnonzero(mask)
    if total and not where.size:
        raise ValueError("no pixel to spread samples over")
    if where.size:
        share, extra = divmod(int(total), where.size)
        counts.flat[where] = share
        counts.flat[where[:extra]] += 1
    return counts


def timed_pass(scene, integrator, counts: np.ndarray, repeats: int, seed: int) -> tuple[float, FrameBuffer]:
    """The fastest of `repeats` identical passes of `counts` into fresh buffers, and the last buffer."""
    best, buffer = float("inf"), None
    for _ in range(repeats):
        buffer = FrameBuffer.empty(*counts.shape)
        start = time.perf_counter()
        render_samples(scene, counts, buffer, integrator=integrator, seed=seed)
        best = min(best, time.perf_counter() - start)
    return best, buffer


def scene_cost(path: str, spp: int, repeats: int) -> dict[str, float]:
    """Seconds for `spp`×pixels samples spread uniformly, over hit pixels, over missed pixels."""
    loop = RenderLoop(LoopSpec(scene=path, spp_first=spp, max_iterations=1, allocator="uniform", denoise=False))
    scene, integrator = loop.scenes[0], loop.integrator
    uniform = np.full(loop.state.buffers[0].shape, spp, np.int64)
    seconds_uniform, buffer = timed_pass(scene, integrator, uniform, repeats, seed=1)
    hit = buffer.depth_sum > 0   # some camera ray of the pixel hit a surface
    total = int(uniform.sum())
    row = {"hit_fraction": float(hit.mean()), "uniform": seconds_uniform}
    for name, mask in (("hit", hit), ("miss", ~hit)):
        row[name] = timed_pass(scene, integrator, spread_over(mask, total), repeats, seed=2)[0] if mask.any() \
            else float("nan")
    return row


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--suite", choices=sorted(SUITES), default="dev")
    parser.add_argument("--spp", type=int, default=32)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--only", nargs="*", default=None)
    args = parser.parse_args()
    print("| scene | pixels hit | uniform s | all on hit pixels s | all on missed pixels s | hit ÷ uniform | miss ÷ hit |\n"
          "|---|---:|---:|---:|---:|---:|---:|")
    for scene in dev_scenes(args.only, SUITES[args.suite].root):
        r = scene_cost(str(scene.path), args.spp, args.repeats)
        print(f"| {scene.name} | {r['hit_fraction']:.2f} | {r['uniform']:.3f} | {r['hit']:.3f} | {r['miss']:.3f} | "
              f"{r['hit'] / r['uniform']:.2f} | {r['miss'] / r['hit']:.2f} |", flush=True)


if __name__ == "__main__":
    main()
