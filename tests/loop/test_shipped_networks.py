"""The shipped networks keep what they were measured to do, on development scenes they never saw
(scenes/dev: hard_shadows, metals, glass_box and env_object, committed 16k/65k-spp references):
an untrained network fails this test."""
from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np
import pytest
import torch
from scipy.stats import spearmanr

from bench.common import image_metrics
from bench.dev_references import DEFAULT_REFERENCE_DIR, dev_scenes, load_reference
from bench.quality_measures import shadow_contrast_ratio
from bench.suite_quality import SHADOW_REGIONS
from models.denoiser import Denoiser
from models.error_predictor import ErrorPredictor
from models.pretrained import Networks, load_networks
from service.loop.loop import RenderLoop
from service.loop.oidn import candidate_for
from service.loop.spec import LoopSpec
from service.loop.tensors import frame_tensors, to_image


@dataclass(frozen=True)
class Guard:
    """What the shipped networks must keep on one scene (the loop's first iteration, 16 spp)."""
    smape_cut: float           # noisy SMAPE ÷ the denoised image's
    kernel_smape_cut: float    # the same for the kernels alone (the candidate's share held at 0)
    error_rank: float          # Spearman of the error network's map against the true error


# Measured with the shipped weights and settings (albedo floor included) on a 2-core AVX2 EPYC
# (float32 trunk; docs/guided-kernels.md has the Xeon's), as cut / kernel cut / rank; an untrained
# network of the shipped architecture in brackets:
#   hard_shadows 5.92 / 4.36 / 0.547  (5.83 / 2.49 / 0.05)   OIDN alone 5.89
#   metals       5.66 / 4.28 / 0.580  (5.59 / 2.22 / 0.29)   OIDN alone 5.51
#   glass_box    4.26 / 3.32 / 0.608  (4.21 / 1.08 / 0.33)   OIDN alone 4.04
#   env_object   5.38 / 4.23 / 0.834  (5.34 / 1.95 / −0.57)  OIDN alone 5.36
# The shipped denoiser mixes OIDN's image in (oidn_candidate) and its gate leans to it at λ = 1
# (gate offsets 2 and 10), so an untrained network of the shipped architecture scores nearly the
# same on the whole image: what the trained weights carry is the kernels, guarded on their own.
# Margins allow for seeds and platforms (a bf16 trunk on CPUs that have it).
GUARDS = {
    "hard_shadows": Guard(smape_cut=5.5, kernel_smape_cut=3.8, error_rank=0.45),
    "metals": Guard(smape_cut=5.2, kernel_smape_cut=3.7, error_rank=0.47),
    "glass_box": Guard(smape_cut=3.9, kernel_smape_cut=2.9, error_rank=0.5),
    "env_object": Guard(smape_cut=5.0, kernel_smape_cut=3.7, error_rank=0.75),
}
# Issue 13: the lattice's hard shadows keep ≥ 90 % of the reference's contrast at λ = 1
# (bench.quality_measures.shadow_contrast_ratio on SHADOW_REGIONS). Measured 0.918 (OIDN 0.963;
# before the gate was fine-tuned, 0.890).
MIN_SHADOW_CONTRAST = 0.9
# A firefly may not darken its surroundings: every ring (Chebyshev distance 1–6 px) around an
# injected 2000× firefly keeps this share of its mean without the firefly. Measured: 0.94–1.01
# over six positions (OIDN alone: 0.92–1.02); before the compositor's floor, 0.43–0.69.
MIN_RING_SHARE_AROUND_A_FIREFLY = 0.9
FIREFLY_FACTOR = 2000.0


def guarded_scene(name: str):
    (scene,) = dev_scenes([name])
    reference, _ = load_reference(DEFAULT_REFERENCE_DIR, scene)
    return scene, reference


@pytest.fixture(scope="module")
def shipped() -> Networks:
    return load_networks()


@pytest.fixture(scope="module")
def shipped_runs(shipped):
    """name → (scene, reference, the shipped networks' first iteration), each rendered once."""
    runs: dict = {}

    def run(name: str):
        if name not in runs:
            scene, reference = guarded_scene(name)
            runs[name] = scene, reference, first_iteration(scene, shipped)
        return runs[name]
    return run


def first_iteration(scene, networks):
    return next(iter(RenderLoop(LoopSpec(scene=str(scene.path), max_iterations=1), networks).run()))


def smape_cut(record, reference) -> float:
    noisy = image_metrics(record.buffers[0].mean, reference)["smape"]
    return noisy / image_metrics(record.denoised[0], reference)["smape"]


def kernel_smape_cut(denoiser: Denoiser, record, reference) -> float:
    """The SMAPE cut of the kernels alone: every level's result before the candidate joins."""
    frame = frame_tensors(record.buffers[0])
    with torch.inference_mode():
        cache = denoiser.prepare([frame], 0, candidate_for(denoiser, frame))
        kernel_levels: list[torch.Tensor] = []
        denoiser.filter_levels(cache, 1.0, kernel_levels)
        kernels = to_image(denoiser.merge_levels(cache, kernel_levels))
    return image_metrics(record.buffers[0].mean, reference)["smape"] / image_metrics(kernels, reference)["smape"]


def true_error(denoised: np.ndarray, reference: np.ndarray) -> np.ndarray:
    return np.abs(denoised - reference).mean(axis=2) / (np.abs(reference).mean(axis=2) + 1e-2)


def error_rank(record, reference) -> float:
    return spearmanr(record.error[0].ravel(), true_error(record.denoised[0], reference).ravel()).correlation


@pytest.mark.parametrize("name", GUARDS)
def test_shipped_denoiser_keeps_its_smape_cut_on_an_unseen_scene(shipped, shipped_runs, name):
    _, reference, record = shipped_runs(name)
    assert smape_cut(record, reference) >= GUARDS[name].smape_cut
    assert kernel_smape_cut(shipped.denoiser, record, reference) >= GUARDS[name].kernel_smape_cut


def test_shipped_denoiser_keeps_the_hard_shadows_contrast(shipped_runs):
    _, reference, record = shipped_runs("hard_shadows")
    assert shadow_contrast_ratio(record.denoised[0], reference, SHADOW_REGIONS["hard_shadows"]) >= MIN_SHADOW_CONTRAST


def untrained_shipped_architecture(shipped: Networks) -> Networks:
    torch.manual_seed(0)
    return Networks(Denoiser(shipped.denoiser.config).eval(), shipped.error_predictor)


@pytest.mark.parametrize("name", GUARDS)
def test_an_untrained_denoiser_does_not_pass_the_guard(shipped, tiny_networks, name):
    scene, reference = guarded_scene(name)
    for networks in (tiny_networks, untrained_shipped_architecture(shipped)):
        record = first_iteration(scene, networks)
        # the whole image of a candidate-leaning architecture is mostly OIDN's: the kernels tell
        assert kernel_smape_cut(networks.denoiser, record, reference) < GUARDS[name].kernel_smape_cut


@pytest.mark.parametrize("name", GUARDS)
def test_shipped_error_network_ranks_pixels_by_their_true_error(shipped_runs, name):
    _, reference, record = shipped_runs(name)
    assert error_rank(record, reference) >= GUARDS[name].error_rank


@pytest.mark.parametrize("name", GUARDS)
def test_an_untrained_error_network_does_not_pass_the_guard(shipped, name):
    scene, reference = guarded_scene(name)
    torch.manual_seed(0)
    untrained = Networks(shipped.denoiser, ErrorPredictor(shipped.error_predictor.config).eval())
    assert error_rank(first_iteration(scene, untrained), reference) < GUARDS[name].error_rank


def denoise_buffer(denoiser, buffer) -> np.ndarray:
    frame = frame_tensors(buffer)
    with torch.inference_mode():
        return to_image(denoiser([frame], 0, 1.0, candidate_for(denoiser, frame)))


def luminance(image: np.ndarray) -> np.ndarray:
    return image @ np.array([0.2126, 0.7152, 0.0722])


def test_a_firefly_leaves_no_dark_halo_around_it(shipped, shipped_runs):
    # One sample FIREFLY_FACTOR× the pixel's mean, injected into a real 16-spp render; the
    # yardstick is the same denoiser on the same render without it, so only the firefly's own
    # effect is measured (the "no halo darker than the surrounding reference").
    denoiser = shipped.denoiser
    buffer = shipped_runs("hard_shadows")[2].buffers[0]
    without = luminance(denoise_buffer(denoiser, buffer))
    rng = np.random.default_rng(0)
    h, w = buffer.shape
    for _ in range(6):
        y, x = int(rng.integers(20, h - 20)), int(rng.integers(20, w - 20))
        injected = copy.deepcopy(buffer)
        value = FIREFLY_FACTOR * max(float(luminance(buffer.mean[y, x])), 0.05) * injected.spp[y, x]
        injected.radiance_sum[y, x] += value
        injected.radiance_sq_sum[y, x] += value * value
        with_firefly = luminance(denoise_buffer(denoiser, injected))
        ys, xs = np.mgrid[y - 6:y + 7, x - 6:x + 7]
        distance = np.maximum(np.abs(ys - y), np.abs(xs - x))
        for ring in range(1, 7):
            inside = distance == ring
            share = with_firefly[ys[inside], xs[inside]].mean() / without[ys[inside], xs[inside]].mean()
            assert share >= MIN_RING_SHARE_AROUND_A_FIREFLY, (y, x, ring, share)
