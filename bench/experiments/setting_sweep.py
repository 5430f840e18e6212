"""One post-training setting of the denoiser, swept on a suite against OIDN (docs/decisions.md: the
energy blocks, the kernel clamp, the gate offset at 16 spp).

A post-training setting (models.denoiser.POST_TRAINING_SETTINGS) is applied by `prepare`/`apply`
without retraining, so each value is tried on the same inputs. Per scene, sample count and seed:
one uniform render, OIDN on the same noisy colour, albedo and normal, and ours at each value.
Each cell is ours ÷ OIDN (SMAPE / relMSE), the geometric mean over the seeds; the summary gives
the medians over the scenes, how many scenes are at most OIDN's, and the mean of the six medians
(16/64/256 spp × SMAPE/relMSE) that chose every post-training setting so far.

    python -m bench.experiments.setting_sweep --setting albedo_floor --values 0 0.05 0.1 0.2
                                              [--suite val|dev] [--spp 16 64 256] [--seeds 1 2 3] [--weights DIR]
"""
from __future__ import annotations

import argparse
import dataclasses
from typing import Sequence

import numpy as np
import torch

from bench.common import denoiser_settings, image_metrics, load_bench_networks, oidn_denoiser, pinned_torch_threads
from bench.dev_references import SUITES, dev_scenes, load_reference
from bench.experiments.seed_spread import paired_ratio
from bench.suite_quality import uniform_render
from models.denoiser import POST_TRAINING_SETTINGS, Denoiser, DenoiserConfig
from models.frames import FrameTensors
from models.pretrained import Networks
from service.loop.denoise_frame import prepare_frame
from service.loop.tensors import frame_tensors, to_image


def setting_images(denoiser: Denoiser, frame: FrameTensors, candidate: torch.Tensor | None, setting: str,
                   values: Sequence[object]) -> list[np.ndarray]:
    """The λ = 1 image for each value of `setting`; the config is back in place after."""
    images = []
    for value in values:
        with denoiser_settings(denoiser, **{setting: value}):
            images.append(to_image(denoiser.apply(denoiser.prepare([frame], 0, candidate))))
    return images


def summary_rows(cells: dict[tuple[int, object], list[tuple[float, float]]], spps: Sequence[int],
                 values: Sequence[object]) -> list[tuple[object, list[tuple[float, int, float, int]], float]]:
    """Per value: per spp (median SMAPE ratio, scenes ≤ OIDN, median relMSE ratio, scenes ≤ OIDN),
    and the mean of all those medians (lower is better)."""
    rows = []
    for value in values:
        per_spp, medians = [], []
        for spp in spps:
            s, r = np.asarray(cells[(spp, value)]).T
            per_spp.append((float(np.median(s)), int((s <= 1).sum()), float(np.median(r)), int((r <= 1).sum())))
            medians += [np.median(s), np.median(r)]
        rows.append((value, per_spp, float(np.mean(medians))))
    return rows


def sweep(networks: Networks, suite: str, setting: str, values: Sequence[object], spps: Sequence[int],
          seeds: Sequence[int]) -> None:
    """Print one row per (scene, spp) as it is measured, then the summary table."""
    denoiser = networks.denoiser
    oidn, _ = oidn_denoiser()
    print(f"ours ÷ OIDN, SMAPE / relMSE, geometric mean over seeds {list(seeds)}; {setting} as below\n\n"
          "| scene | spp | " + " | ".join(f"{setting} {v}" for v in values) + " |\n|---|---:|" + "---|" * len(values))
    cells: dict[tuple[int, object], list[tuple[float, float]]] = {}
    with pinned_torch_threads(2), torch.no_grad():
        for scene in dev_scenes(None, SUITES[suite].root):
            reference, _ = load_reference(SUITES[suite].references, scene, None if scene.frames == 1 else 0)
            for spp in spps:
                # per value: (ours, OIDN) SMAPE and relMSE, one row per seed
                per_value: dict[object, list[tuple[float, float, float, float]]] = {v: [] for v in values}
                for seed in seeds:
                    buffer = uniform_render(scene, spp, networks, seed=seed).buffers[0]
                    theirs = image_metrics(oidn(buffer.mean, buffer.albedo, buffer.normal), reference)
                    frame = frame_tensors(buffer)
                    candidate = prepare_frame(denoiser, [frame], 0).candidate   # fetched once, reused per value
                    for value, image in zip(values, setting_images(denoiser, frame, candidate, setting, values)):
                        ours = image_metrics(image, reference)
                        per_value[value].append((ours["smape"], theirs["smape"], ours["relmse"], theirs["relmse"]))
                means = {}
                for value, rows in per_value.items():
                    ours_s, theirs_s, ours_r, theirs_r = np.asarray(rows).T
                    means[value] = (paired_ratio(ours_s, theirs_s).geometric_mean,
                                    paired_ratio(ours_r, theirs_r).geometric_mean)
                    cells.setdefault((spp, value), []).append(means[value])
                print(f"| {scene.name} | {spp} | " + " | ".join(f"{s:.3f} / {r:.3f}" for s, r in means.values()) + " |",
                      flush=True)
    print(f"\n| {setting} | " + " | ".join(f"{spp} spp: SMAPE (≤ OIDN) / relMSE (≤ OIDN)" for spp in spps)
          + " | mean of the medians |\n|---:|" + "---|" * len(spps) + "---:|")
    for value, per_spp, mean in summary_rows(cells, spps, values):
        print(f"| {value} | " + " | ".join(f"{s:.4f} ({ns} of {len(cells[(spp, value)])}) / {r:.4f} "
                                           f"({nr} of {len(cells[(spp, value)])})"
                                           for spp, (s, ns, r, nr) in zip(spps, per_spp)) + f" | {mean:.4f} |")


def parse_values(setting: str, texts: Sequence[str]) -> list[object]:
    """Each text as the setting's own type: on/off for a flag, 'off' or 'none' for a setting that may be None."""
    default = next(f.default for f in dataclasses.fields(DenoiserConfig) if f.name == setting)
    kind = bool if isinstance(default, bool) else int if isinstance(default, int) else float
    values: list[object] = []
    for text in texts:
        if kind is bool:
            values.append(text.lower() in ("1", "true", "on"))
        elif text.lower() in ("off", "none"):
            values.append(None)
        else:
            values.append(kind(text))
    return values


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--setting", required=True, choices=POST_TRAINING_SETTINGS)
    parser.add_argument("--values", nargs="+", required=True)
    parser.add_argument("--suite", choices=sorted(SUITES), default="val")
    parser.add_argument("--spp", type=int, nargs="+", default=[16, 64, 256])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--weights", default=None, help="folder of denoiser.pt and error_predictor.pt (default: shipped)")
    args = parser.parse_args(argv)
    try:
        values = parse_values(args.setting, args.values)
    except ValueError as e:
        parser.error(f"--values: {e}")
    sweep(load_bench_networks(args.weights).networks, args.suite, args.setting, values, args.spp, args.seeds)


if __name__ == "__main__":
    main()
