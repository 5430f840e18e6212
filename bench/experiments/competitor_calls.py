"""What does splitting `mi.render`'s spp into short calls cost a stratifying scene?
(bench/versus_mitsuba_scene.pass_plan; docs/decisions.md, "The `mi.render` competitor renders
each level in as few calls as the sampler allows")

Over 16 samples Mitsuba's `stratified` sampler is biased, so a level rendered as many 16-spp calls
averaged is not what a user's own call gives. For each stratifying scene of scenes/dev and
scenes/val, at its committed reference's size (about 256²), the scene as written rendered at SPP
with its albedo and normals twice — in calls of 16 spp and in calls of 64 (the competitor's plan
since 02f4612: the largest power of 4 that divides the level) — then OIDN; printed per scene the
SMAPE of each (the mean over the seeds), their ratio and each image mean's offset from the
reference, then the median and geometric mean of the ratios.

    python -m bench.experiments.competitor_calls [--spp 128] [--seeds 0 1] [--scenes A,B]
"""
from __future__ import annotations

import argparse
import statistics

import numpy as np

from bench.common import oidn_denoiser
from bench.dev_references import still_scenes
from bench.versus_mitsuba_run import MITSUBA_SEED, image_smape
from bench.versus_mitsuba_scene import Film, competitor_scene, render_with_aovs, scene_sampler
from service.render.scenes import STRATIFYING_SAMPLER_PLUGINS

CALL_SPP = (16, 64)  # the old 2 MP competitor's calls, and the fewest a stratifying sampler takes at 128
SEED_STRIDE = 1000   # seeds of one method's runs must not share call seeds


def split_smapes(scene, reference: np.ndarray, spp: int, seeds: list[int], oidn) -> dict[int, tuple[float, float]]:
    """Per samples-per-call: (SMAPE after OIDN averaged over `seeds`, the last image mean's
    relative offset from the reference)."""
    height, width = reference.shape[:2]
    loaded = competitor_scene(scene, Film(width, height))
    out = {}
    for per_call in CALL_SPP:
        smapes, offset = [], 0.0
        for seed in seeds:
            image = render_with_aovs(loaded, spp, MITSUBA_SEED + SEED_STRIDE * seed,
                                     max_lanes=per_call * width * height)
            smapes.append(image_smape(oidn(image.color, image.albedo, image.normal), reference))
            offset = float(image.color.mean() / reference[..., :3].mean() - 1.0)
        out[per_call] = (statistics.fmean(smapes), offset)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--spp", type=int, default=128)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--scenes", type=lambda text: text.split(","), default=None)
    args = parser.parse_args(argv)
    oidn, _ = oidn_denoiser()
    ratios = []
    short, long = CALL_SPP
    for suite in ("dev", "val"):
        for scene, reference in still_scenes(suite):
            if scene_sampler(scene) not in STRATIFYING_SAMPLER_PLUGINS or (args.scenes and scene.name not in args.scenes):
                continue
            result = split_smapes(scene, reference, args.spp, args.seeds, oidn)
            ratio = result[short][0] / result[long][0]
            ratios.append(ratio)
            print(f"{scene.name:18s} {scene_sampler(scene):12s} SMAPE after OIDN, calls of {short}: {result[short][0]:.4f}, "
                  f"of {long}: {result[long][0]:.4f}, ratio {ratio:.3f}; image mean offset "
                  f"{result[short][1]:+.3%} / {result[long][1]:+.3%}", flush=True)
    if ratios:
        print(f"{len(ratios)} scenes: ratio median {statistics.median(ratios):.3f}, "
              f"geometric mean {float(np.exp(np.mean(np.log(ratios)))):.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
