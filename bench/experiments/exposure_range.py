"""Which exposures did the networks learn on? (models/exposure.py; docs/decisions.md,
"Exposure normalisation, kept")

Renders the noisy 16-spp input of procedural training scenes (the data set's own scene
generator and renderer, training seeds) and prints the distribution of the exposure statistic
E (models.exposure.exposure_metric) over them, and E of the dev and val suites' scenes for
comparison: models.exposure.TRAINED_EXPOSURE and EXPOSURE_KEY are read from it.

    python -m bench.experiments.exposure_range [--scenes 97] [--size 128] [--spp 16] [--suites]
"""
from __future__ import annotations

import argparse

import numpy as np

from bench.dev_references import SUITES, dev_scenes
from models.exposure import EXPOSURE_KEY, TRAINED_EXPOSURE, exposure_metric
from service.dataset.procedural import sample_spec, scene_dict
from service.dataset.splits import scene_seeds
from service.loop.loop import RenderLoop
from service.loop.spec import LoopSpec
from service.loop.tensors import nchw
from service.render.framebuffer import FrameBuffer
from service.render.renderer import render_samples
from service.render.runtime import mitsuba


def training_exposures(scenes: int, size: int, spp: int) -> list[float]:
    """E of the `spp`-sample input of the first `scenes` training scenes (data-set seed 0)."""
    mi = mitsuba()
    values = []
    for seed in scene_seeds("train", scenes, 0):
        scene = mi.load_dict(scene_dict(sample_spec(seed), size=size, frame=0))
        buffer = FrameBuffer.empty(size, size)
        render_samples(scene, np.full((size, size), spp), buffer, seed=seed)
        values.append(float(exposure_metric(nchw(buffer.mean))[0]))
    return values


def suite_exposures(spp: int) -> dict[str, float]:
    """E of each dev and val scene's uniform `spp` render (bench's own scene lists)."""
    out = {}
    for suite, root in SUITES.items():
        for scene in dev_scenes(root=root.root):
            spec = LoopSpec(scene=str(scene.path), spp_first=spp, max_iterations=1, allocator="uniform", denoise=False)
            buffer = next(iter(RenderLoop(spec).run())).buffers[0]
            out[f"{suite}/{scene.name}"] = float(exposure_metric(nchw(buffer.mean))[0])
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=97)
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--suites", action="store_true", help="also E of the dev and val scenes")
    args = parser.parse_args()
    values = np.array(training_exposures(args.scenes, args.size, args.spp))
    finite = values[np.isfinite(values)]
    print(f"training scenes: {len(values)} ({args.size}², {args.spp} spp), E finite on {len(finite)}")
    for q in (0, 1, 5, 10, 50, 90, 95, 99, 100):
        print(f"  p{q:<3} E = {np.percentile(finite, q):.4g}")
    lo, hi = TRAINED_EXPOSURE
    print(f"  TRAINED_EXPOSURE = [{lo}, {hi}]: {np.mean((finite >= lo) & (finite <= hi)):.0%} of these inside; "
          f"every image is moved to EXPOSURE_KEY = {EXPOSURE_KEY}")
    if args.suites:
        for name, e in suite_exposures(args.spp).items():
            print(f"  {name:<32} E = {e:.4g}  (scaled by {EXPOSURE_KEY / e:.3g})")


if __name__ == "__main__":
    main()
