"""The shipped networks keep what they were measured to do, on a development scene they never saw
(scenes/dev/hard_shadows, committed 16k-spp reference): an untrained network fails this test."""
from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from bench.common import image_metrics
from bench.dev_references import DEFAULT_REFERENCE_DIR, dev_scenes, load_reference
from bench.quality_measures import shadow_contrast_ratio
from bench.suite_quality import SHADOW_REGIONS
from models.denoiser import Denoiser
from models.pretrained import Networks, load_networks
from service.loop.loop import RenderLoop
from service.loop.oidn import candidate_for
from service.loop.spec import LoopSpec
from service.loop.tensors import frame_tensors, to_image

# Measured with the shipped weights (the loop's first iteration, 16 spp; docs/guided-kernels.md):
# SMAPE cut 5.93× (OIDN alone 5.89×); the error network's per-pixel Spearman correlation with the
# true error of that image 0.570 (0.530 before it was fine-tuned against the guided denoiser,
# docs/error-network.md; an untrained error network: −0.23).
# The shipped denoiser mixes OIDN's image in (oidn_candidate) and its gate leans to it at λ = 1
# (gate offsets 2 and 10), so an untrained network of the shipped architecture also scores 5.85×
# on the whole image: what the trained weights carry is the kernels, guarded on their own (the
# candidate's share held at 0): 4.35× shipped (3.02× before the kernels read OIDN's image),
# 2.48× untrained. Margins allow for seeds and platforms.
MIN_SMAPE_CUT = 5.5
MIN_KERNEL_SMAPE_CUT = 3.8
MIN_ERROR_RANK_CORRELATION = 0.45
# Issue 13: the lattice's hard shadows keep ≥ 90 % of the reference's contrast at λ = 1
# (bench.quality_measures.shadow_contrast_ratio on SHADOW_REGIONS). Measured 0.918 (OIDN 0.963;
# before the gate was fine-tuned, 0.890).
MIN_SHADOW_CONTRAST = 0.9
# A firefly may not darken its surroundings: every ring (Chebyshev distance 1–6 px) around an
# injected 2000× firefly keeps this share of its mean without the firefly. Measured: 0.94–1.01
# over six positions (OIDN alone: 0.92–1.02); before the compositor's floor, 0.43–0.69.
MIN_RING_SHARE_AROUND_A_FIREFLY = 0.9
FIREFLY_FACTOR = 2000.0


@pytest.fixture(scope="module")
def hard_shadows():
    (scene,) = dev_scenes(["hard_shadows"])
    reference, _ = load_reference(DEFAULT_REFERENCE_DIR, scene)
    return scene, reference


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


def test_shipped_denoiser_keeps_its_smape_cut_on_an_unseen_scene(hard_shadows):
    scene, reference = hard_shadows
    networks = load_networks()
    record = first_iteration(scene, networks)
    assert smape_cut(record, reference) >= MIN_SMAPE_CUT
    assert kernel_smape_cut(networks.denoiser, record, reference) >= MIN_KERNEL_SMAPE_CUT


def test_shipped_denoiser_keeps_the_hard_shadows_contrast(hard_shadows):
    scene, reference = hard_shadows
    denoised = first_iteration(scene, load_networks()).denoised[0]
    assert shadow_contrast_ratio(denoised, reference, SHADOW_REGIONS["hard_shadows"]) >= MIN_SHADOW_CONTRAST


def untrained_shipped_architecture() -> Networks:
    shipped = load_networks()
    torch.manual_seed(0)
    return Networks(Denoiser(shipped.denoiser.config).eval(), shipped.error_predictor)


@pytest.mark.parametrize("untrained", ["tiny", "shipped-architecture"])
def test_an_untrained_denoiser_does_not_pass_the_guard(hard_shadows, tiny_networks, untrained):
    scene, reference = hard_shadows
    networks = tiny_networks if untrained == "tiny" else untrained_shipped_architecture()
    record = first_iteration(scene, networks)
    # the whole image of a candidate-leaning architecture is mostly OIDN's: the kernels tell
    assert kernel_smape_cut(networks.denoiser, record, reference) < MIN_KERNEL_SMAPE_CUT


def test_shipped_error_network_ranks_pixels_by_their_true_error(hard_shadows):
    from scipy.stats import spearmanr

    scene, reference = hard_shadows
    record = first_iteration(scene, load_networks())
    true = np.abs(record.denoised[0] - reference).mean(axis=2) / (np.abs(reference).mean(axis=2) + 1e-2)
    correlation = spearmanr(record.error[0].ravel(), true.ravel()).correlation
    assert correlation >= MIN_ERROR_RANK_CORRELATION


def denoise_buffer(denoiser, buffer) -> np.ndarray:
    frame = frame_tensors(buffer)
    with torch.inference_mode():
        return to_image(denoiser([frame], 0, 1.0, candidate_for(denoiser, frame)))


def luminance(image: np.ndarray) -> np.ndarray:
    return image @ np.array([0.2126, 0.7152, 0.0722])


def test_a_firefly_leaves_no_dark_halo_around_it(hard_shadows):
    # One sample FIREFLY_FACTOR× the pixel's mean, injected into a real 16-spp render; the
    # yardstick is the same denoiser on the same render without it, so only the firefly's own
    # effect is measured (the "no halo darker than the surrounding reference").
    scene, _ = hard_shadows
    denoiser = load_networks().denoiser
    buffer = first_iteration(scene, load_networks()).buffers[0]
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
