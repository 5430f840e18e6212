"""Does averaging the error network over dihedral views of its inputs (models/error_tta.py) rank
pixels better? Paired on the same inputs: each scene's calibration loop (bench/calibration_report.py)
runs with the plain network, so every variant is scored on exactly the frames the plain one saw;
per call the variants are computed beside it (2/4/8 views, mean or geometric mean; a 3×3 or 5×5
box blur of the map; the geometric mean with the previous iteration's map). Per scene, seed and
iteration: the per-pixel and 8×8-tile Spearman of each map against the true SMAPE map.

    python -m bench.experiments.error_tta --suite val -o /tmp/error-tta/paired-val.json

The loop's SMAPE at equal samples with the views in charge of the allocation is the loop report's,
with the views chosen at start-up: RENDERLOOP_ERROR_VIEWS=4 renderloop bench --loop --suite dev ...
"""
from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from bench.calibration_report import calibration_spec
from bench.common import load_bench_networks, pinned_torch_threads, true_error_map
from bench.dev_references import SUITES, dev_scenes, load_reference
from bench.quality_measures import block_means, spearman
from models.error_predictor import ErrorMap
from models.error_tta import ErrorTTA
from models.frames import FrameTensors
from models.pretrained import Networks
from service.loop.loop import RenderLoop

ITERATIONS = 5            # the calibration report's 16 → 256 spp
FIRST_ONLY_SEEDS = (1000, 1001, 1002, 1003)   # more 16-spp renders, as the report's ceiling takes
BLOCK = 8


def box_blur(error: Tensor, size: int) -> Tensor:
    return F.avg_pool2d(F.pad(error, (size // 2,) * 4, mode="replicate"), size, stride=1)


class VariantRecorder:
    """An ErrorMap that answers with the plain network and records every variant's map beside it."""

    def __init__(self, network: ErrorMap) -> None:
        self.network = network
        self.views = {f"v{k}{c[0]}": ErrorTTA(network, k, c) for k in (2, 4, 8) for c in ("mean", "geometric")}
        self.calls: list[dict[str, np.ndarray]] = []
        self.seconds: dict[str, list[float]] = {}

    @property
    def change_scale(self) -> float | None:
        return self.network.change_scale

    @property
    def reads_disagreement(self) -> bool:
        return self.network.reads_disagreement

    def _timed(self, name: str, network: ErrorMap, *inputs) -> Tensor:
        started = time.perf_counter()
        out = network(*inputs)
        self.seconds.setdefault(name, []).append(time.perf_counter() - started)
        return out

    @torch.no_grad()
    def __call__(self, frame: FrameTensors, denoised: Tensor, disagreement: Tensor | None = None) -> Tensor:
        plain = self._timed("v1", self.network, frame, denoised, disagreement)
        maps = {"v1": plain} | {name: self._timed(name, tta, frame, denoised, disagreement)
                                for name, tta in self.views.items()}
        for size in (3, 5):
            maps[f"v1_box{size}"], maps[f"v8m_box{size}"] = box_blur(plain, size), box_blur(maps["v8m"], size)
        self.calls.append({name: m[0, 0].numpy().copy() for name, m in maps.items()})
        return plain


def score_iterations(records: list, calls: list[dict[str, np.ndarray]], reference) -> list[dict]:
    rows, previous = [], None
    for it, (record, maps) in enumerate(zip(records, calls)):
        true = true_error_map(record.denoised[0], reference)
        if previous is not None:
            for name in ("v1", "v8m"):
                maps[f"{name}_prev"] = np.sqrt(np.maximum(maps[name], 1e-8) * np.maximum(previous[name], 1e-8))
        row = {"it": it, "spp": record.spp_mean}
        for name, m in maps.items():
            row[name] = spearman(m, true)
            row[f"{name}_b"] = spearman(block_means(m, BLOCK), block_means(true, BLOCK))
        rows.append(row)
        previous = maps
    return rows


def measure(suite: str, seeds: tuple[int, ...]) -> dict:
    nets = load_bench_networks(None).networks
    recorder = VariantRecorder(nets.error_predictor)
    networks = Networks(nets.denoiser, recorder)
    rows = []
    with pinned_torch_threads(1):
        for scene in dev_scenes(None, SUITES[suite].root):
            reference, _ = load_reference(SUITES[suite].references, scene, None if scene.frames == 1 else 0)
            for seed, iterations in [(s, ITERATIONS) for s in seeds] + [(s, 1) for s in FIRST_ONLY_SEEDS]:
                recorder.calls = []
                records = list(RenderLoop(calibration_spec(scene.path, iterations=iterations, seed=seed), networks).run())
                for row in score_iterations(records, recorder.calls[-iterations:], reference):
                    rows.append({"scene": scene.name, "seed": seed, **row})
                print(scene.name, seed, " ".join(f"{r['it']}:{r['v1']:.3f}/{r['v8m']:.3f}" for r in rows
                                                 if r["scene"] == scene.name and r["seed"] == seed), flush=True)
    return {"rows": rows, "seconds": {k: statistics.median(v) for k, v in recorder.seconds.items()}}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--suite", choices=("dev", "val"), default="val")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    p.add_argument("-o", "--out", type=Path, required=True, help="JSON of every row")
    args = p.parse_args(argv)
    args.out.write_text(json.dumps(measure(args.suite, tuple(args.seeds))))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
