"""`renderloop denoise` on the EXRs Mitsuba writes itself, and what the estimated variance costs
(docs/fidelity.md, "Mitsuba's own checks, the scene's sample count, Mitsuba's EXRs").

1. `mi.render` of `mi.cornell_box()` at SIZE², SPP spp, with an `aov` integrator
   (albedo, sh_normal, depth) around `path`, for a box and a Gaussian film, SEEDS seeds, each
   denoised by service.exr_denoise.denoise_exr; SMAPE of the raw and the denoised image against a
   REFERENCE_SPP `mi.render` of the same film.
2. Our own EXRs of the built-in cornell-box (`renderloop render --no-denoise`, which carry the
   true variance of the mean) denoised with that layer and without it (then estimated from the
   image): SMAPE against an OUR_REFERENCE_SPP render, the estimate against the true variance, and
   the error network's mean prediction with each.

    python -m bench.experiments.mitsuba_exr_denoise
"""
from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from models.pretrained import load_networks
from service.exr import read_exr, write_exr
from service.exr_denoise import denoise_exr, estimate_variance
from service.loop.spec import LoopSpec
from service.loop.loop import RenderLoop
from service.loop.tensors import configure_torch_threads
from service.render.runtime import mitsuba

SIZE, SPP, SEEDS = 64, 16, 3
REFERENCE_SPP = 4096
OUR_SEEDS, OUR_REFERENCE_SPP = 2, 2048
AOVS = "albedo:albedo,nn:sh_normal,dd:depth"
SMAPE_EPS = 1e-2  # Vogels et al. 2018, eq. 2


def smape(image: np.ndarray, reference: np.ndarray) -> float:
    return float(np.mean(np.abs(image - reference) / (np.abs(image) + np.abs(reference) + SMAPE_EPS)))


def cornell_box(rfilter: str, integrator: dict, spp: int):
    mi = mitsuba()
    scene = mi.cornell_box()
    scene["sensor"]["film"].update(width=SIZE, height=SIZE, rfilter={"type": rfilter})
    scene["sensor"]["sampler"] = {"type": "independent", "sample_count": spp}
    scene["integrator"] = integrator
    return mi.load_dict(scene)


def mitsuba_films(networks, folder: Path) -> None:
    mi = mitsuba()
    for rfilter in ("box", "gaussian"):
        reference = np.asarray(mi.render(cornell_box(rfilter, {"type": "path"}, REFERENCE_SPP), seed=99))[..., :3]
        rows = []
        for seed in range(SEEDS):
            scene = cornell_box(rfilter, {"type": "aov", "aovs": AOVS, "img": {"type": "path"}}, SPP)
            mi.render(scene, seed=seed)
            path = folder / f"{rfilter}_{seed}.exr"
            scene.sensors()[0].film().bitmap().write(str(path))
            denoised = denoise_exr(path, folder / f"{rfilter}_{seed}_denoised.exr", networks, spp=SPP)
            rows.append((smape(read_exr(path).color, reference), smape(denoised.color, reference)))
        raw, ours = np.mean(rows, axis=0)
        print(f"{rfilter}: mi.render {SPP} spp raw SMAPE {raw:.4f}, renderloop denoise {ours:.4f} ({SEEDS} seeds)")


def our_render(spp: int, seed: int, path: Path) -> Path:
    spec = LoopSpec(scene="cornell-box", width=SIZE, height=SIZE, spp_first=spp, max_iterations=1, denoise=False,
                    seed=seed)
    loop = RenderLoop(spec, None)
    for _ in loop.run():
        pass
    return write_exr(path, loop.result_frames()[0])


def estimated_variance(networks, folder: Path) -> None:
    reference = read_exr(our_render(OUR_REFERENCE_SPP, 123, folder / "reference.exr")).noisy
    for seed in range(OUR_SEEDS):
        path = our_render(SPP, seed, folder / f"ours_{seed}.exr")
        frame = read_exr(path)
        true_variance = frame.variance
        with_true = denoise_exr(path, folder / f"ours_{seed}_true.exr", networks)
        # The estimate written as the variance layer: the image `denoise` makes of a file without
        # one, and what the error network (which `denoise` then skips) would read from it.
        estimated = estimate_variance(frame.noisy)
        frame.variance = estimated
        with_estimate = denoise_exr(write_exr(folder / f"ours_{seed}_estimate.exr", frame),
                                    folder / f"ours_{seed}_estimated.exr", networks)
        ratio = estimated / np.maximum(true_variance, 1e-8)
        print(f"seed {seed}: SMAPE with the true variance {smape(with_true.color, reference):.4f}, with the estimate "
              f"{smape(with_estimate.color, reference):.4f}; estimate / true: mean "
              f"{estimated.mean() / true_variance.mean():.2f}, median pixel {np.median(ratio):.2f}; mean predicted SMAPE "
              f"{with_true.error.mean():.4f} with the true variance, {with_estimate.error.mean():.4f} with the estimate "
              f"(true {smape(with_true.color, reference):.4f})")


def main() -> None:
    configure_torch_threads()
    networks = load_networks(None)
    with tempfile.TemporaryDirectory(prefix="mitsuba-exr-") as folder:
        mitsuba_films(networks, Path(folder))
        estimated_variance(networks, Path(folder))


if __name__ == "__main__":
    main()
