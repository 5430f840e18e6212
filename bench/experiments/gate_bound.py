"""What could a better candidate gate give? (docs/oidn-candidate.md, "What a perfect gate could give")

Per scene at one uniform sample count: the shipped denoiser, OIDN, the denoiser's kernels alone
(the candidate suppressed), and two oracles that pick per pixel, or per 8×8 neighbourhood, the
lower true error of the two — bounds that no gate reading only the inputs can beat.

    python -m bench.experiments.gate_bound [SPP] [--suite val|dev] [--weights DIR]
"""
from __future__ import annotations

import argparse

import numpy as np
import torch
from scipy.ndimage import uniform_filter

from bench.common import image_metrics, load_bench_networks, pinned_torch_threads, true_error_map
from bench.dev_references import SUITES, dev_scenes, load_reference
from bench.suite_quality import uniform_render
from models.denoiser import Denoiser
from models.kernel_disagreement import apply_with_kernels_image
from service.loop.oidn import candidate_for
from service.loop.tensors import frame_tensors, to_image

NEIGHBOURHOOD = 8


def kernels_and_candidate(denoiser: Denoiser, frame) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The shipped output at λ = 1, its kernels' image alone, and OIDN's image (each (1, 3, H, W))."""
    candidate = candidate_for(denoiser, frame)
    output, kernels = apply_with_kernels_image(denoiser, denoiser.prepare([frame], 0, candidate))
    return output, kernels, candidate


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("spp", type=int, nargs="?", default=16)
    parser.add_argument("--suite", choices=sorted(SUITES), default="val")
    parser.add_argument("--weights", default=None, help="folder of denoiser.pt and error_predictor.pt (default: shipped)")
    args = parser.parse_args()
    nets = load_bench_networks(args.weights)
    denoiser = nets.networks.denoiser
    print("| scene | ours | OIDN | kernels alone | per-pixel oracle | 8×8 oracle |\n|---|---:|---:|---:|---:|---:|")
    with pinned_torch_threads(2), torch.no_grad():
        for scene in dev_scenes(None, SUITES[args.suite].root):
            reference, _ = load_reference(SUITES[args.suite].references, scene, None if scene.frames == 1 else 0)
            frame = frame_tensors(uniform_render(scene, args.spp, nets.networks).buffers[0])
            ours, kernels, oidn = (to_image(image) for image in kernels_and_candidate(denoiser, frame))
            error_k, error_o = true_error_map(kernels, reference), true_error_map(oidn, reference)
            per_pixel = np.where((error_k < error_o)[..., None], kernels, oidn)
            smooth_k, smooth_o = (uniform_filter(e, NEIGHBOURHOOD) for e in (error_k, error_o))
            per_block = np.where((smooth_k < smooth_o)[..., None], kernels, oidn)
            scores = [image_metrics(x, reference)["smape"] for x in (ours, oidn, kernels, per_pixel, per_block)]
            print(f"| {scene.name} | " + " | ".join(f"{v:.4f}" for v in scores) + " |", flush=True)


if __name__ == "__main__":
    main()
