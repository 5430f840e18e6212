"""`renderloop bench --dev-suite`: the product against what a user would use instead, on the
hand-written development scenes (never trained on) and their committed references.

Per scene: a 16-spp uniform render denoised by our KPCN and by OIDN (same inputs), and at a
128-spp mean the adaptive loop against a uniform 128-spp render + OIDN, with wall times.
"""
from __future__ import annotations

import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench.common import (OidnDenoise, fill, fmt, image_metrics, load_bench_networks, oidn_denoiser,
                          pinned_torch_threads, provenance)
from bench.dev_references import DEFAULT_REFERENCE_DIR, DevScene, dev_scenes, load_reference
from models.pretrained import Networks
from service.loop.loop import RenderLoop
from service.loop.spec import LoopSpec
from service.render.runtime import active_variant

REPORT_NAME = "dev-suite.md"
FIRST_SPP = 16
LOOP_ITERATIONS = 4  # 16 → 32 → 64 → 128 spp mean
FINAL_SPP = FIRST_SPP * 2 ** (LOOP_ITERATIONS - 1)
TORCH_THREADS = 1  # see bench/loop_report.py: more threads measure the neighbours on a shared host


@dataclass(frozen=True)
class SceneScores:
    scene: str
    noisy16: float
    kpcn16: float
    oidn16: float
    loop128: float
    uniform128_oidn: float
    loop_seconds: float
    uniform_oidn_seconds: float


def _smape(image: np.ndarray, reference: np.ndarray) -> float:
    return image_metrics(image, reference)["smape"]


def score_scene(scene: DevScene, reference: np.ndarray, networks: Networks, oidn: OidnDenoise) -> SceneScores:
    """Every method on one scene (frame 0 of a sequence), each from its own loop."""
    def spec(**fields) -> LoopSpec:
        return LoopSpec(scene=str(scene.path), **fields)

    first = next(iter(RenderLoop(spec(max_iterations=1, spp_first=FIRST_SPP), networks).run()))
    buffer = first.buffers[0]
    oidn16 = oidn(buffer.mean, buffer.albedo, buffer.normal)

    started = time.perf_counter()
    for record in RenderLoop(spec(max_iterations=LOOP_ITERATIONS, spp_first=FIRST_SPP), networks).run():
        pass
    loop_seconds = time.perf_counter() - started

    started = time.perf_counter()
    uniform = next(iter(RenderLoop(spec(max_iterations=1, spp_first=FINAL_SPP, denoise=False,
                                        allocator="uniform"), None).run()))
    ubuf = uniform.buffers[0]
    uniform_oidn = oidn(ubuf.mean, ubuf.albedo, ubuf.normal)
    uniform_seconds = time.perf_counter() - started

    return SceneScores(
        scene.name, _smape(buffer.mean, reference), _smape(first.denoised[0], reference), _smape(oidn16, reference),
        _smape(record.denoised[0], reference), _smape(uniform_oidn, reference), loop_seconds, uniform_seconds)


def run_dev_suite_report(out_dir: Path, *, weights_dir: Path | None = None, only: list[str] | None = None,
                         reference_dir: Path = DEFAULT_REFERENCE_DIR) -> Path:
    oidn, oidn_note = oidn_denoiser()
    nets = load_bench_networks(weights_dir)
    rows = []
    with pinned_torch_threads(TORCH_THREADS):
        for scene in dev_scenes(only):
            reference, header = load_reference(reference_dir, scene, None if scene.frames == 1 else 0)
            scores = score_scene(scene, reference, nets.networks, oidn)
            print(f"bench --dev-suite: {scene.name}: KPCN16 {scores.kpcn16:.4f} OIDN16 {scores.oidn16:.4f} "
                  f"loop128 {scores.loop128:.4f} uniform128+OIDN {scores.uniform128_oidn:.4f}", flush=True)
            rows.append(scores)
    return write_dev_suite_report(rows, out_dir, oidn_note, nets.description)


def write_dev_suite_report(rows: list[SceneScores], out_dir: Path, oidn_note: str, weights: str) -> Path:
    table = "\n".join(
        f"| {r.scene} | {fmt(r.noisy16)} | {fmt(r.kpcn16)} | {fmt(r.oidn16)} | {fmt(r.loop128)} | "
        f"{fmt(r.uniform128_oidn)} | {r.loop_seconds:.1f} | {r.uniform_oidn_seconds:.1f} |" for r in rows)
    median = lambda attribute: fmt(statistics.median(getattr(r, attribute) for r in rows))  # noqa: E731
    path = out_dir / REPORT_NAME
    out_dir.mkdir(parents=True, exist_ok=True)
    path.write_text(fill(
        "dev_suite.md", provenance=provenance(variant=active_variant()),
        reference_note="scenes/dev/references: mi.render as written, 16 384 spp, 65 536 for the three noisiest",
        oidn=oidn_note, weights=weights, table=table, count=len(rows),
        median_noisy=median("noisy16"), median_kpcn=median("kpcn16"), median_oidn=median("oidn16"),
        median_loop=median("loop128"), median_uniform=median("uniform128_oidn"),
        kpcn_wins=sum(r.kpcn16 < r.oidn16 for r in rows), loop_wins=sum(r.loop128 < r.uniform128_oidn for r in rows),
        wall_ratio=fmt(statistics.median(r.loop_seconds / r.uniform_oidn_seconds for r in rows), ".2f")))
    return path
