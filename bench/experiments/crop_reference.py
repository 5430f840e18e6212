"""Does a ~2 MP reading stand against a stronger reference? (docs/decisions.md, "fog_spot at 2 MP")

`renderloop bench --versus-mitsuba` scores each ~2 MP image against a 1024-spp reference (2 G
samples; more is hours here). Where light arrives by rare paths (a spot light through fog) such a
reference is heavy-tailed: its typical pixel sits below the truth, and per-pixel SMAPE and relMSE
against it reward an image that drops those paths' energy. Many more samples are affordable on a
few windows of the film. This renders the loop as the report does (error allocator, 16 spp then
doubling; with the denoiser's energy factor and without it) and `mi.render` + OIDN with a box film
(the stronger competitor on such scenes) at the report's film size, and scores both on four
windows — the centres of the film's quarters, a margin dropped where a window's own render lacks
its neighbours' splats — against those windows rendered with --crop-spp samples (`independent`,
cached in --cache) and, on the same pixels, against the cache's full-film reference if it has one.
Times are not taken: read them from the report's curves.

    python -m bench.experiments.crop_reference --scene fog_spot --megapixels 2 --crop-spp 8192 --spp 16 32 64
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from bench.common import denoiser_settings, image_metrics, load_bench_networks, oidn_denoiser, pinned_torch_threads
from bench.experiments.energy_tolerance import UNTOUCHED, median_pixel_ratio
from bench.loop_report import DEFAULT_CACHE_DIR
from bench.versus_mitsuba import suite_scenes
from bench.versus_mitsuba_run import FIRST_SPP, MITSUBA_SEED, make_loop, spp_levels
from bench.versus_mitsuba_scene import (Crop, Film, competitor_scene, reference, reference_path,
                                        render_with_aovs, scaled_film)

WINDOW = (128, 96)   # pixels of each crop: four of them at 8192 spp took 16 min for fog_spot here
MARGIN = 4           # a Gaussian film's splat reaches 2 px (Mitsuba's radius 4σ, σ = 0.5): twice that


def quarter_crops(film: Film, width: int = WINDOW[0], height: int = WINDOW[1]) -> list[Crop]:
    """Windows of width × height centred on the centres of the film's four quarters."""
    return [Crop(round(film.width * fx) - width // 2, round(film.height * fy) - height // 2, width, height)
            for fx in (0.25, 0.75) for fy in (0.25, 0.75)]


def scored(window: np.ndarray, margin: int = MARGIN) -> np.ndarray:
    """A window's pixels less `margin` on each side."""
    return window[margin:window.shape[0] - margin, margin:window.shape[1] - margin]


def window_scores(images: list[np.ndarray], references: list[np.ndarray]) -> tuple[float, float, float]:
    """(SMAPE, relMSE, median pixel ÷ reference's) over the pixels of every window together."""
    image = np.concatenate([scored(x).reshape(-1, 3) for x in images])[None]
    ref = np.concatenate([scored(x).reshape(-1, 3) for x in references])[None]
    metrics = image_metrics(image, ref)
    return metrics["smape"], metrics["relmse"], median_pixel_ratio(image, ref)


def loop_windows(scene, film: Film, crops: list[Crop], networks, levels: list[int], factor: bool) -> dict[int, list[np.ndarray]]:
    """The loop's final image at each level (error allocator), cut to the windows; without the
    energy factor if not `factor` (the samples' energy trusted with weight ~0)."""
    denoiser = networks.denoiser
    tolerance = denoiser.config.energy_tolerance if factor else UNTOUCHED
    images = {}
    with denoiser_settings(denoiser, energy_tolerance=tolerance):
        for record in make_loop(scene, film, networks, "error", len(levels)).run():
            images[round(record.spp_mean)] = [crop.of(record.denoised[0]) for crop in crops]
    return images


def mitsuba_windows(scene, film: Film, crops: list[Crop], levels: list[int]) -> dict[int, list[np.ndarray]]:
    """`mi.render` with a box film, its albedo and normals, then OIDN, at each level, cut to the windows."""
    oidn, _ = oidn_denoiser()
    loaded = competitor_scene(scene, film, box=True)
    images = {}
    for spp in levels:
        image = render_with_aovs(loaded, spp, MITSUBA_SEED)
        images[spp] = [crop.of(oidn(image.color, image.albedo, image.normal)) for crop in crops]
    return images


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--scene", required=True, help="a suite scene (scenes/dev or scenes/val)")
    parser.add_argument("--megapixels", type=float, default=2.0)
    parser.add_argument("--crop-spp", type=int, default=8192, help="the windows' reference")
    parser.add_argument("--spp", type=int, nargs="+", default=[16, 32, 64], help="the loop's totals: 16, 32, 64 …")
    parser.add_argument("--reference-spp", type=int, default=1024, help="the full-film reference, if the cache has it")
    parser.add_argument("--cache", type=Path, default=DEFAULT_CACHE_DIR)
    args = parser.parse_args()
    levels = spp_levels(max(*args.spp, FIRST_SPP))
    if not set(args.spp) <= set(levels):
        parser.error(f"--spp values are the loop's totals: {', '.join(map(str, spp_levels(64)))} …")
    scene = suite_scenes([args.scene])[0]
    film = scaled_film(scene, args.megapixels)
    crops = quarter_crops(film)
    strong = [reference(scene, film, args.crop_spp, args.cache, crop).mean for crop in crops]
    full_path = reference_path(scene, film, args.reference_spp, args.cache)
    full = ([crop.of(reference(scene, film, args.reference_spp, args.cache).mean) for crop in crops]
            if full_path.is_file() else None)
    nets = load_bench_networks(None)
    with pinned_torch_threads(2), torch.no_grad():
        methods = {"the loop": loop_windows(scene, film, crops, nets.networks, levels, factor=True),
                   "the loop, energy factor off": loop_windows(scene, film, crops, nets.networks, levels, factor=False),
                   "`mi.render` + OIDN, box film": mitsuba_windows(scene, film, crops, args.spp)}
    print(f"{scene.name} at {film}, windows {', '.join(str(c) for c in crops)} less {MARGIN} px; "
          f"references: the windows at {args.crop_spp} spp"
          + (f", the film's at {args.reference_spp} spp" if full else ""))
    if full:
        smape, _, median = window_scores(full, strong)
        print(f"the {args.reference_spp}-spp reference against the {args.crop_spp}-spp one: SMAPE {smape:.4f}, median pixel {median:.4f}")
    print(f"\n| method | spp | SMAPE, relMSE, median pixel against {args.crop_spp} spp |"
          + (f" the same against {args.reference_spp} spp |" if full else "") + "\n|---|---:|---|" + ("---|" if full else ""))
    for label, images in methods.items():
        for spp in args.spp:
            cells = [window_scores(images[spp], strong)] + ([window_scores(images[spp], full)] if full else [])
            print(f"| {label} | {spp} | " + " | ".join(f"{s:.4f}, {r:.3g}, {m:.4f}" for s, r, m in cells) + " |", flush=True)


if __name__ == "__main__":
    main()
