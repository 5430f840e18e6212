"""How much can ANY allocation of the loop's samples gain over uniform? (docs/error-network.md,
"The most any allocation can gain")

Issue 14 asks for SMAPE (d)/(b) ≤ 0.85 at equal samples. The loop benchmark's oracle (o), the
allocator fed the denoised image's true error, reaches a median 0.89 (docs/benchmarks-dev.md);
this asks the question without the allocator's particulars. Per scene, K renders that differ
only in their seed are denoised by the shipped denoiser at 16 and at 128 spp uniform; the mean
of their true SMAPE maps is the scene's expected error ē₁₆, ē₁₂₈. Model each pixel's expected
denoised error as e_i(n) = v_i·n^−β (the paper's allocation, Vogels et al. 2018 §7, is driven by
such a per-pixel error), with β fitted to the scene's mean errors (ē₁₂₈ = ē₁₆·8^−β) and
v_i = ē₁₂₈,i·128^β. With the first 16 spp spent uniformly, as the loop does, the allocation of a
mean 128 spp that minimises Σ e_i(n_i) is a Lagrange optimum (`optimal_counts`). Its error ÷
uniform's is the most that any allocation knowing the expected error exactly can gain, under the
model:

- **pixel**: each pixel's samples lower only its own error;
- **shared 5×5**: v box-filtered over 5×5 pixels first — the denoiser spreads a pixel's samples
  over its neighbours, so samples cannot be aimed finer than its kernels;
- **tiles, own β**: 8×8 tiles, each with its own fitted exponent (where the error is bias that
  more samples barely lower, β is small and the tile is not worth feeding).

A predictor that reads one render's inputs can also see that render's own luck (a firefly), which
the expected error cannot: (o) is fed the realised error, so it can land below these figures.

    python -m bench.experiments.allocation_bound [--suite val|dev] [--renders 4]
"""
from __future__ import annotations

import argparse
import math

import numpy as np
import torch
from scipy.ndimage import uniform_filter

from bench.common import denoise_and_predict, load_bench_networks, pinned_torch_threads, true_error_map
from bench.dev_references import SUITES, still_scenes
from bench.quality_measures import block_means
from bench.suite_quality import uniform_render
from models.pretrained import Networks
from service.loop.tensors import frame_tensors, to_image

FIRST_SPP, FINAL_SPP = 16, 128   # the loop's first pass and its mean after four iterations
SHARED_WIDTH = 5                 # the shipped kernels' width at the finest level
TILE = 8                         # the calibration report's tile size
FIRST_SEED = 200                 # away from the other experiments' seeds


def fitted_exponent(error_low: np.ndarray | float, error_high: np.ndarray | float,
                    spp_low: int = FIRST_SPP, spp_high: int = FINAL_SPP) -> np.ndarray | float:
    """β of e ∝ n^−β through (spp_low, error_low) and (spp_high, error_high), elementwise."""
    tiny = 1e-12
    return np.log(np.maximum(error_low, tiny) / np.maximum(error_high, tiny)) / math.log(spp_high / spp_low)


def optimal_counts(v: np.ndarray, beta: np.ndarray, first_spp: float, mean_spp: float) -> np.ndarray:
    """Counts n ≥ first_spp with mean mean_spp minimising Σ v_i·n_i^−β_i: where n_i > first_spp
    the marginal gains β_i·v_i·n_i^(−β_i−1) all equal one μ, so n_i = max(first_spp,
    (β_i·v_i/μ)^(1/(1+β_i))); the total falls monotonically in μ, found by bisection in log μ."""
    v, beta = np.maximum(v, 0.0), np.maximum(beta, 1e-3)
    def counts(log_mu: float) -> np.ndarray:
        with np.errstate(divide="ignore"):
            return np.maximum(first_spp, np.exp((np.log(beta * v) - log_mu) / (1.0 + beta)))
    lo, hi = -200.0, 200.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if counts(mid).mean() > mean_spp else (lo, mid)
    return counts(hi)


def best_allocation_ratio(error_final: np.ndarray, beta: np.ndarray | float,
                          first_spp: int = FIRST_SPP, final_spp: int = FINAL_SPP) -> float:
    """Σ e_i(n_i*) ÷ Σ e_i(final_spp) for e_i(n) = v_i·n^−β_i with e_i(final_spp) = error_final:
    the optimal counts n* (first_spp already spent everywhere, a mean of final_spp) against
    uniform final_spp. 1 when the error is the same everywhere; the more it varies, the lower."""
    e = np.asarray(error_final, dtype=np.float64).ravel().clip(min=0.0)
    b = np.broadcast_to(np.asarray(beta, dtype=np.float64), np.shape(error_final)).ravel().clip(min=1e-3)
    if not e.sum() > 0:
        return 1.0
    v = e * float(final_spp) ** b
    return float((v * optimal_counts(v, b, first_spp, final_spp) ** -b).sum() / e.sum())


def scene_bounds(expected_first: np.ndarray, expected_final: np.ndarray) -> dict[str, float]:
    """One scene's fitted β and the three bounds of the module text, from its expected error maps
    at FIRST_SPP and FINAL_SPP."""
    beta = float(fitted_exponent(expected_first.mean(), expected_final.mean()))
    low, high = block_means(expected_first, TILE), block_means(expected_final, TILE)
    return {
        "beta": beta,
        "pixel": best_allocation_ratio(expected_final, beta),
        "shared 5×5": best_allocation_ratio(uniform_filter(expected_final, SHARED_WIDTH, mode="nearest"), beta),
        "tiles, own β": best_allocation_ratio(high, fitted_exponent(low, high).clip(0.0, 1.5)),
    }


def expected_error(scene, reference: np.ndarray, networks: Networks, spp: int, renders: int) -> np.ndarray:
    """Mean true SMAPE map of the shipped denoiser's result over `renders` uniform renders."""
    maps = []
    for k in range(renders):
        buffer = uniform_render(scene, spp, networks, seed=FIRST_SEED + k).buffers[0]
        _, denoised, _ = denoise_and_predict(networks.denoiser, networks.error_predictor, [frame_tensors(buffer)], 0)
        maps.append(true_error_map(to_image(denoised), reference))
    return np.mean(maps, axis=0)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--suite", choices=sorted(SUITES), default="dev")
    parser.add_argument("--renders", type=int, default=4)
    args = parser.parse_args()
    nets = load_bench_networks(None)
    columns = ("beta", "pixel", "shared 5×5", "tiles, own β")
    print(f"{args.renders} renders per scene at {FIRST_SPP} and {FINAL_SPP} spp; best allocation's SMAPE ÷ "
          f"uniform's at a mean {FINAL_SPP} spp\n\n| scene | " + " | ".join(columns) + " |\n|---|" + "---:|" * len(columns))
    rows = []
    with pinned_torch_threads(2), torch.no_grad():
        for scene, reference in still_scenes(args.suite):
            first, final = (expected_error(scene, reference, nets.networks, spp, args.renders)
                            for spp in (FIRST_SPP, FINAL_SPP))
            rows.append(scene_bounds(first, final))
            print(f"| {scene.name} | " + " | ".join(f"{rows[-1][c]:.3f}" for c in columns) + " |", flush=True)
    print("| **median** | " + " | ".join(f"**{np.median([r[c] for r in rows]):.3f}**" for c in columns) + " |")


if __name__ == "__main__":
    main()
