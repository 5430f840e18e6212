"""The renderer's throughput against `mi.render` at ~1080p for several wavefront sizes (lanes per
chunk): which `max_wavefront` the GPU wants. Prints one line per case; the device run
(bench/gpu_run.sh) keeps them in its log.

    python -m bench.wavefront_probe [--size 1920x1080] [--spp 16] [--repeats 3] [--history]

Our passes add to one FrameBuffer, as the loop's passes do: a fresh buffer per pass also times
the first touch of its ~400 MB of new pages (1.2 s of a 1080p pass's host time on the 2-core
LLVM host, against 0.06-0.15 s with the buffer kept), which no loop iteration after the first
pays. `--history` prints both, with the host's share: wall − Dr.Jit's kernel time.
"""
from __future__ import annotations

import argparse
import statistics
import time

import drjit as dr
import numpy as np

from bench.common import recorded_kernels
from service.render.framebuffer import FrameBuffer
from service.render.renderer import render_samples
from service.render.runtime import active_variant, mitsuba
from service.render.scenes import load_scene

WAVEFRONTS = (1 << 22, 1 << 23, 1 << 24, 1 << 25)


def _seconds(call, repeats: int) -> float:
    call()  # compiles the kernels (cached for the timed calls)
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        call()
        times.append(time.perf_counter() - started)
    return statistics.median(times)


def probe(scene_name: str, width: int, height: int, spp: int, repeats: int) -> None:
    mi = mitsuba()
    scene = load_scene(scene_name, width=width, height=height)
    samples = width * height * spp
    # mi.render in calls of at most 2^25 lanes, as bench --versus-mitsuba renders
    per_call = max(1, min(spp, (1 << 25) // (width * height)))

    def theirs() -> None:
        for i in range(spp // per_call):
            image = mi.render(scene, spp=per_call, seed=i)
            dr.eval(image)
        np.asarray(image)

    base = _seconds(theirs, repeats)
    print(f"wavefront probe [{active_variant()}] {scene_name} {width}x{height} {spp} spp: mi.render "
          f"{samples / base / 1e6:.1f} M samples/s", flush=True)
    for label, counts in count_maps(width, height, spp).items():
        for lanes in WAVEFRONTS if label == "uniform" else (WAVEFRONTS[0],):
            buffer = FrameBuffer.empty(height, width)
            ours = _seconds(lambda: render_samples(scene, counts, buffer, max_wavefront=lanes), repeats)
            print(f"wavefront probe [{active_variant()}] {scene_name} {label} counts, max_wavefront "
                  f"2^{lanes.bit_length() - 1}: ours {int(counts.sum()) / ours / 1e6:.1f} M samples/s = "
                  f"{base / ours * counts.sum() / samples:.2f}x mi.render", flush=True)


def count_maps(width: int, height: int, spp: int) -> dict[str, np.ndarray]:
    """A uniform pass (the loop's first) and an uneven one of the same mean, like an adaptive
    pass's (counts 1 … 2·spp − 1, uniformly at random)."""
    uneven = np.random.default_rng(0).integers(1, 2 * spp, size=(height, width))
    return {"uniform": np.full((height, width), spp), "uneven": uneven}


def kernel_history(label: str, call) -> None:
    """Dr.Jit's kernel history of one call: how many kernels it launched and their GPU time
    against the call's wall time (where the rest goes: the host)."""
    with recorded_kernels() as history:
        started = time.perf_counter()
        call()
        wall = time.perf_counter() - started
    kernels = [k for k in history if "execution_time" in k]
    gpu_ms = sum(float(k["execution_time"]) for k in kernels)
    print(f"kernel history {label}: wall {wall * 1e3:.0f} ms, {len(history)} entries, {len(kernels)} timed, "
          f"kernel time {gpu_ms:.0f} ms, host (wall - kernel) {wall * 1e3 - gpu_ms:.0f} ms", flush=True)
    for k in sorted(kernels, key=lambda k: -float(k["execution_time"]))[:6]:
        print(f"  {float(k['execution_time']):8.1f} ms  {k.get('type')} size {k.get('size')} "
              f"ops {k.get('operation_count')} hash {str(k.get('hash'))[:10]}", flush=True)


def scatter_probe(pixels: int, spp: int, channels: int = 13) -> None:
    """The per-pixel sums' scatter-add alone (lanes of one pixel consecutive), per ReduceMode."""
    mi = mitsuba()
    lanes = pixels * spp
    idx = dr.arange(mi.UInt32, lanes) // spp
    value = dr.full(mi.Float, 0.5, lanes)
    for mode in (dr.ReduceMode.Auto, dr.ReduceMode.Local, dr.ReduceMode.Direct):
        def run() -> None:
            sums = dr.zeros(mi.Float, pixels * channels)
            for c in range(channels):
                dr.scatter_reduce(dr.ReduceOp.Add, sums, value, idx * channels + c, mode=mode)
            dr.eval(sums)
            dr.sync_thread()
        seconds = _seconds(run, 3)
        print(f"scatter probe {pixels} px x {spp} lanes x {channels} ch, {mode}: {seconds * 1e3:.1f} ms", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="1920x1080")
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--scenes", default="cornell-box")
    parser.add_argument("--history", action="store_true", help="also Dr.Jit's kernel history of one pass each, "
                        "and the per-pixel sums' scatter alone per reduce mode")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    for name in args.scenes.split(","):
        probe(name, width, height, args.spp, args.repeats)
    if args.history:
        mi = mitsuba()
        scene = load_scene("cornell-box", width=width, height=height)
        for label, counts in count_maps(width, height, args.spp).items():
            buffer = FrameBuffer.empty(height, width)
            render_samples(scene, counts, buffer)   # compiles; the loop's buffer, its pages touched
            kernel_history(f"ours {label}, kept buffer", lambda: render_samples(scene, counts, buffer))
            kernel_history(f"ours {label}, fresh buffer",
                           lambda: render_samples(scene, counts, FrameBuffer.empty(height, width)))
        kernel_history("mi.render", lambda: np.asarray(mi.render(scene, spp=args.spp)))
        scatter_probe(width * height, args.spp)


if __name__ == "__main__":
    main()
