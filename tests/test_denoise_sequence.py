"""`renderloop denoise --frames`: the shipped single-frame denoiser pools a still sequence's samples
(models/accumulation.py), so the middle frame of three seeds comes out closer to the reference
than the same frame denoised alone."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from bench.common import image_metrics
from models.pretrained import load_networks
from service.exr import read_exr, result_frame, write_exr
from service.exr_denoise import denoise_exr
from service.loop.loop import RenderLoop
from service.loop.spec import LoopSpec

SIZE = 32


def uniform_render(spp: int, seed: int):
    spec = LoopSpec(scene="cornell-box", width=SIZE, height=SIZE, spp_first=spp, max_iterations=1,
                    allocator="uniform", denoise=False, seed=seed)
    return next(iter(RenderLoop(spec, None).run())).buffers[0]


def test_denoising_a_still_sequence_pools_the_neighbours_samples(tmp_path: Path):
    paths = []
    for seed in (1, 2, 3):
        buffer = uniform_render(8, seed)
        paths.append(write_exr(tmp_path / f"f{seed}.exr", result_frame(buffer, buffer.mean, error=None, lam=None,
                                                                       header={})))
    reference = uniform_render(1024, 9).mean
    networks = load_networks()
    alone = denoise_exr(paths[1], tmp_path / "alone.exr", networks)
    pooled = denoise_exr(paths[1], tmp_path / "pooled.exr", networks, frames=paths)
    assert image_metrics(pooled.color, reference)["smape"] < 0.85 * image_metrics(alone.color, reference)["smape"]
    written = read_exr(tmp_path / "pooled.exr")
    assert written.error is not None and np.isfinite(written.error).all()
    # the error network read the pooled counts: it predicts less error than for the frame alone
    assert written.error.mean() < read_exr(tmp_path / "alone.exr").error.mean()
