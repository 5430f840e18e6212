"""How far should the candidate gate lean to OIDN on hand-written scenes? (docs/decisions.md,
"The gate's offsets and the compositor's caps")

The gate was trained on procedural scenes, where the kernels hold their own against OIDN; on
hand-written scenes they are 1.1–5× worse at 16 spp (docs/decisions.md, "The kernels lose at 16 spp"), so a gate
that trusts them as much as in training mixes in too much of them. One logit offset b added to
the finest level's gate logit (DenoiserConfig.gate_offset), and one bc to the coarser levels'
(coarse_gate_offset), move the gate towards the candidate (> 0) without retraining. Per scene,
sample count and setting (b, bc, cap): SMAPE and relMSE of ours and of OIDN, the renders and the
network's preparation shared by every setting.

    python -m bench.experiments.gate_offset [--suite val|dev] [--spp 16 64 256] [--offsets 0 1 2] [--coarse 2 10]
                                            [--cap off on] [--clamp off 0.5] [--weights DIR]

Without --coarse, bc = b (one offset for every level). --cap crosses every pair with the
compositor's candidate cap off and/or on (DenoiserConfig.candidate_cap; without it, the checkpoint's own).
"""
from __future__ import annotations

import argparse

import numpy as np
import torch

from bench.common import denoiser_settings, image_metrics, load_bench_networks, pinned_torch_threads
from bench.dev_references import SUITES, dev_scenes, load_reference
from bench.suite_quality import uniform_render
from models.denoiser import Denoiser
from models.frames import FrameTensors
from service.loop.denoise_frame import prepare_frame
from service.loop.tensors import frame_tensors, to_image

DEFAULT_OFFSETS = (0.0, 1.0, 2.0, 3.0, 4.0)


Setting = tuple[float, float, bool, float | None]   # (b, bc, candidate cap, kernel clamp)


def offset_ratios(denoiser: Denoiser, frame: FrameTensors, candidate: torch.Tensor, reference: np.ndarray,
                  oidn: dict[str, float], settings: list[Setting]) -> list[tuple[float, float]]:
    """(ours ÷ OIDN SMAPE, ours ÷ OIDN relMSE) per (b, bc, cap, clamp) at λ = 1, from one preparation
    (oidn: the candidate's own scores); the denoiser's config is back in place afterwards, whatever happens."""
    cache = denoiser.prepare([frame], 0, candidate)
    ratios = []
    for b, bc, cap, clamp in settings:
        with denoiser_settings(denoiser, gate_offset=b, coarse_gate_offset=bc, candidate_cap=cap, kernel_clamp=clamp):
            ours = image_metrics(to_image(denoiser.apply(cache)), reference)
        ratios.append((ours["smape"] / oidn["smape"], ours["relmse"] / oidn["relmse"]))
    return ratios


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--suite", choices=sorted(SUITES), default="val")
    parser.add_argument("--spp", type=int, nargs="+", default=[16, 64, 256])
    parser.add_argument("--offsets", type=float, nargs="+", default=list(DEFAULT_OFFSETS))
    parser.add_argument("--coarse", type=float, nargs="+", default=None,
                        help="offsets of the coarser levels, each paired with every --offsets value")
    parser.add_argument("--cap", choices=("off", "on"), nargs="+", default=None,
                        help="the compositor's candidate cap (DenoiserConfig.candidate_cap), crossed with every pair")
    parser.add_argument("--clamp", type=_clamp, nargs="+", default=None,
                        help="the kernels' clamp around the candidate (DenoiserConfig.kernel_clamp; 'off' or t), "
                             "crossed with every setting; without it, the checkpoint's own")
    parser.add_argument("--weights", default=None, help="folder of denoiser.pt and error_predictor.pt (default: shipped)")
    args = parser.parse_args()
    nets = load_bench_networks(args.weights)
    denoiser = nets.networks.denoiser
    caps = [c == "on" for c in args.cap] if args.cap else [denoiser.config.candidate_cap]
    clamps = args.clamp or [denoiser.config.kernel_clamp]
    pairs = [(b, b if args.coarse is None else bc, cap, clamp)
             for b in args.offsets for bc in (args.coarse or [None]) for cap in caps for clamp in clamps]
    head = " | ".join(f"b={b:g}, bc={bc:g}, cap {'on' if cap else 'off'}, clamp {_clamp_text(clamp)}"
                      for b, bc, cap, clamp in pairs)
    print(f"SMAPE / relMSE ÷ OIDN's (< 1: ours better)\n\n| scene | spp | OIDN SMAPE | {head} |\n"
          "|---|---:|---:|" + "---:|" * len(pairs))
    ratios: dict[tuple[int, float, float, bool, float | None], list[tuple[float, float]]] = {}
    with pinned_torch_threads(2), torch.no_grad():
        for scene in dev_scenes(None, SUITES[args.suite].root):
            reference, _ = load_reference(SUITES[args.suite].references, scene, None if scene.frames == 1 else 0)
            for spp in args.spp:
                frame = frame_tensors(uniform_render(scene, spp, nets.networks).buffers[0])
                candidate = prepare_frame(denoiser, [frame], 0).candidate   # the shipped path's OIDN image
                oidn = image_metrics(to_image(candidate), reference)
                cells = []
                for pair, ratio in zip(pairs, offset_ratios(denoiser, frame, candidate, reference, oidn, pairs)):
                    ratios.setdefault((spp, *pair), []).append(ratio)
                    cells.append(f"{ratio[0]:.3f} / {ratio[1]:.3f}")
                print(f"| {scene.name} | {spp} | {oidn['smape']:.4f} | " + " | ".join(cells) + " |", flush=True)
    print("\n| spp | b | bc | cap | clamp | median SMAPE ÷ OIDN | ≤ OIDN SMAPE | median / mean relMSE ÷ OIDN | ≤ OIDN relMSE |\n"
          "|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for (spp, b, bc, cap, clamp), values in sorted(ratios.items(), key=lambda kv: (kv[0][:4], -1.0 if kv[0][4] is None else kv[0][4])):
        s, r = np.array(values).T
        print(f"| {spp} | {b:g} | {bc:g} | {'on' if cap else 'off'} | {_clamp_text(clamp)} | {np.median(s):.3f} | {(s <= 1).sum()} of {len(s)} "
              f"| {np.median(r):.3f} / {r.mean():.3f} | {(r <= 1).sum()} of {len(r)} |")


def _clamp(text: str) -> float | None:
    return None if text == "off" else float(text)


def _clamp_text(clamp: float | None) -> str:
    return "off" if clamp is None else f"{clamp:g}"


if __name__ == "__main__":
    main()
