"""The shipped networks keep what they were measured to do, on development scenes they never saw
(scenes/dev: hard_shadows, metals, glass_box and env_object, committed 16k/65k-spp references),
and each guard rejects what it guards against: an untrained network of the shipped architecture,
OIDN alone, a √variance map posing as the error network (the planted-bug pattern of
tests/fidelity/test_planted_bugs.py)."""
from __future__ import annotations

import copy
import math
import sys
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

import numpy as np
import pytest
import torch

from bench.common import image_metrics, true_error_map
from bench.quality_measures import shadow_contrast_ratio, spearman
from bench.suite_quality import SHADOW_REGIONS
from models.denoiser import Denoiser
from models.error_predictor import ErrorPredictor
from models.pretrained import Networks, load_networks
from service.loop.denoise_frame import denoise_frame, prepare_frame
from service.loop.oidn import oidn_image
from service.loop.tensors import frame_tensors, to_image

from dev_scene_runs import DevRun, final_image_of_samples, loop_on_samples, render_dev_runs

SCENES = ("hard_shadows", "metals", "glass_box", "env_object")
UNTRAINED_SEEDS = (0, 1, 2)

# --- the whole-image guard: what our denoiser adds over OIDN alone ---------------------------------
# The shipped denoiser mixes OIDN's image in (oidn_candidate) and its gate leans to it, so every
# denoiser of that architecture, trained or not, lands near OIDN on the whole image: a bar on the
# noisy ÷ denoised SMAPE cut that the shipped network clears is cleared by OIDN alone too (hard_shadows
# 5.90 vs OIDN 5.89). The guard asks for the difference, on the same render (the loop's first
# iteration, 16 spp; its final image, which falls back towards the raw samples where they are
# expected to be closer, service/loop/final_image.py): SMAPE against OIDN's over the four scenes'
# 216 whole 32² crops, and per scene.
# Measured by `python tests/loop/test_shipped_networks.py` (main, below) on a 2-core AVX2 EPYC
# (float32 trunk), shipped / untrained of the shipped architecture (seeds 0–2, the loop's final
# image of the shipped run's own samples: final_image_of_samples) / OIDN alone, at dedcf86:
#   geometric mean of the crops' SMAPE ÷ OIDN's   0.8245 / 0.8366–0.8383 / 1
#   share of the crops where ours beats OIDN      0.708 / 0.606–0.620 / 0
#   per scene: hard_shadows 0.998 / 1.008–1.009, metals 0.961 / 1.014–1.015,
#              glass_box 0.962 / 1.024–1.040, env_object 0.954 / 0.942–0.943
# (the same in two runs. Metals renders as another noise realisation in some processes, see
# final_image_of_samples; a third one, with Mitsuba's mesh merging off: metals 0.957 / 1.006–1.007,
# pooled 0.8243 / 0.8364–0.8380, crops won 0.713 / 0.616–0.625. At 9722499, the final image's
# fallback reading outliers on both sides, the untrained pooled figure fell from 0.845–0.849 at
# 1184da7 to within 0.001 of the old bar 0.834.)
# Other renders, `main 1` and `main 2` (the loop's seed): pooled 0.8226 / 0.8341–0.8354 and
# 0.8271 / 0.8414–0.8440, crops won 0.722 / 0.597–0.606 and 0.764 / 0.657–0.667, every scene of
# the shipped network ≤ 0.989. Over the three renders the pooled bar sits halfway between the
# shipped network's worst and the untrained networks' best (0.0039 and 0.0031 either side), the
# crops bar 0.028 under the shipped worst and 0.013 over the untrained best; earlier figures in
# docs/decisions.md. No scene may end up worse than OIDN.
MAX_CROP_SMAPE_RATIO_TO_OIDN = 0.831
MIN_SHARE_OF_CROPS_BEATING_OIDN = 0.68
MAX_SCENE_SMAPE_RATIO_TO_OIDN = 1.005
CROP = 32


@dataclass(frozen=True)
class Guard:
    """What the shipped networks must keep on one scene beyond the whole-image guard."""
    kernel_smape_cut: float    # noisy SMAPE ÷ the kernels' alone (the candidate's share held at 0)
    error_rank: float          # Spearman of the error network's map against the true error


# Measured as for the whole-image guard (at 9722499), kernel cut / rank, shipped (untrained of the
# shipped architecture: kernels seed 0 / error networks seeds 0, 1) [best √variance ÷ denoised map
# over five ways of forming it, see sqrt_variance_maps], loop seed 0, then the shipped rank and the
# best √variance map at loop seeds 1 and 2:
#   hard_shadows 4.13 / 0.529  (2.49 / 0.065, 0.025)   [0.089]   seeds 1, 2: 0.547 [0.090], 0.502 [0.084]
#   metals       3.16 / 0.593  (1.52 / 0.110, −0.054)  [0.189]               0.589 [0.216], 0.622 [0.188]
#   glass_box    3.02 / 0.663  (0.93 / 0.254, 0.184)   [0.591]               0.647 [0.555], 0.606 [0.589]
#   env_object   4.17 / 0.836  (1.96 / −0.605, −0.605) [0.698]               0.838 [0.698], 0.832 [0.694]
# (kernel cuts at loop seeds 1 and 2 within 0.15 of seed 0's; metals at loop seed 0 in a process
# that renders it as another noise realisation, see final_image_of_samples: 3.08 / 0.605 (1.44)
# [0.180], dedcf86.) Rank bars sit between the shipped network and
# the √variance map over all three loop seeds: glass_box's halfway between the maps' 0.591 and
# the shipped 0.606 of loop seed 2 (it was 0.626, which that render's shipped network failed).
GUARDS = {
    "hard_shadows": Guard(kernel_smape_cut=3.8, error_rank=0.45),
    "metals": Guard(kernel_smape_cut=2.8, error_rank=0.47),
    "glass_box": Guard(kernel_smape_cut=2.9, error_rank=0.598),
    "env_object": Guard(kernel_smape_cut=3.7, error_rank=0.75),
}
# No-regression checks at λ = 1 (they do not tell trained from untrained: an untrained network of the
# shipped architecture leans on OIDN as the shipped one does and keeps 0.942 of the contrast and
# ring shares ≥ 0.9997; OIDN alone 0.957 and ≥ 0.999). Issue 13: the lattice's hard shadows keep
# ≥ 90 % of the reference's contrast at λ = 1 (bench.quality_measures.shadow_contrast_ratio on
# SHADOW_REGIONS); measured 0.942 (before the gate was fine-tuned, 0.890).
MIN_SHADOW_CONTRAST = 0.9
# A firefly may not darken its surroundings: every ring (Chebyshev distance 1–6 px) around an
# injected 2000× firefly keeps this share of its mean without the firefly. Measured ≥ 0.949 over
# six positions; before the compositor's floor, 0.43–0.69.
MIN_RING_SHARE_AROUND_A_FIREFLY = 0.9
FIREFLY_FACTOR = 2000.0

# --- what λ = 10 buys: the shadow and firefly guards ------------------------------------------------
# At λ = 1 the shipped denoiser's shadows and fireflies are OIDN's (its gate leans to the candidate):
# contrast 0.942 vs OIDN 0.957, a firefly's 13² window SMAPE ×1.15–6.2 for both and the untrained
# network. What only a trained network gives is λ (Vogels et al. 2018, eq. 6: λ > 1 weighs up errors
# that cross the reference away from the input): at λ = 10 the hard shadows' edges keep more contrast
# than OIDN's and a firefly stays on its pixel. An untrained λ module blurs both; OIDN has no λ.
# Measured by `python tests/loop/test_shipped_networks.py [SEED]` (main) on hard_shadows' 16-spp
# first iteration, loop seeds 0/1/2, shipped / untrained seeds 0–2 / OIDN alone:
#   edge-band contrast ÷ OIDN's        1.051/1.046/1.048 / 0.814–0.836 / 1
#   worst window SMAPE × (6 fireflies) 1.44/1.35/1.36    / ≥ 27.2      / 6.17/6.25/5.22
# The contrast bar sits halfway between OIDN and the shipped network (0.023 either side; the
# render seeds spread 0.005); the firefly bar near the geometric mean of shipped and OIDN.
DETAIL_LAMBDA = 10.0
MIN_SHADOW_EDGE_CONTRAST_TO_OIDN = 1.023
MAX_FIREFLY_WINDOW_SMAPE_GROWTH = 2.5
FIREFLY_WINDOW = 6   # the window's half side: the rings of the halo check


@pytest.fixture(scope="module")
def shipped() -> Networks:
    return load_networks()


@pytest.fixture(scope="module")
def dev_runs(shipped) -> dict[str, DevRun]:
    """Each scene rendered once for the whole module."""
    return render_dev_runs(shipped, SCENES)


# --- the whole-image guard --------------------------------------------------------------------------

def smape(image: np.ndarray, reference: np.ndarray) -> float:
    return image_metrics(image, reference)["smape"]


def crop_smapes(image: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Mean SMAPE of every whole CROP² crop of the image, row by row."""
    error = true_error_map(image, reference)
    h, w = error.shape
    return np.array([error[y:y + CROP, x:x + CROP].mean()
                     for y in range(0, h - CROP + 1, CROP) for x in range(0, w - CROP + 1, CROP)])


@dataclass(frozen=True)
class WholeImageFigures:
    pooled: float                   # geometric mean over the crops of SMAPE ÷ OIDN's
    crops_won: float                # share of the crops where the image's SMAPE is below OIDN's
    scene_ratios: dict[str, float]  # per scene, SMAPE ÷ OIDN's


def whole_image_figures(denoised: dict[str, np.ndarray], runs: dict[str, DevRun]) -> WholeImageFigures:
    crop_ratios = np.concatenate([crop_smapes(denoised[name], run.reference) / crop_smapes(run.oidn, run.reference)
                                  for name, run in runs.items()])
    return WholeImageFigures(math.exp(float(np.mean(np.log(crop_ratios)))), float(np.mean(crop_ratios < 1.0)),
                             {name: smape(denoised[name], run.reference) / smape(run.oidn, run.reference)
                              for name, run in runs.items()})


def whole_image_failures(denoised: dict[str, np.ndarray], runs: dict[str, DevRun]) -> list[str]:
    """The whole-image guard on one denoised image per scene: [] when it passes, else what failed."""
    figures = whole_image_figures(denoised, runs)
    failures = []
    if figures.pooled > MAX_CROP_SMAPE_RATIO_TO_OIDN:
        failures.append(f"pooled: crops' SMAPE ÷ OIDN's {figures.pooled:.4f} > {MAX_CROP_SMAPE_RATIO_TO_OIDN}")
    if figures.crops_won < MIN_SHARE_OF_CROPS_BEATING_OIDN:
        failures.append(f"crops: beats OIDN on {figures.crops_won:.3f} of them < {MIN_SHARE_OF_CROPS_BEATING_OIDN}")
    failures += [f"{name}: SMAPE ÷ OIDN's {ratio:.4f} > {MAX_SCENE_SMAPE_RATIO_TO_OIDN}"
                 for name, ratio in figures.scene_ratios.items() if ratio > MAX_SCENE_SMAPE_RATIO_TO_OIDN]
    return failures


def untrained_shipped_architecture(shipped: Networks, seed: int) -> Networks:
    torch.manual_seed(seed)
    return Networks(Denoiser(shipped.denoiser.config).eval(), shipped.error_predictor)


def untrained_images(shipped: Networks, seed: int, runs: dict[str, DevRun]) -> dict[str, np.ndarray]:
    """name → the loop's final image of the run's own samples with an untrained denoiser of the
    shipped architecture (final_image_of_samples)."""
    networks = untrained_shipped_architecture(shipped, seed)
    return {name: final_image_of_samples(run, networks) for name, run in runs.items()}


def test_networks_measured_on_a_runs_samples_get_the_loops_own_final_image(shipped, dev_runs):
    # what makes final_image_of_samples the loop's first iteration with other networks: with the
    # shipped ones it gives back the shipped run's final image, bit for bit
    run = dev_runs["hard_shadows"]
    assert np.array_equal(final_image_of_samples(run, shipped), run.record.denoised[0])


def test_shipped_denoiser_adds_to_oidn_on_the_whole_image(dev_runs):
    assert whole_image_failures({name: run.record.denoised[0] for name, run in dev_runs.items()}, dev_runs) == []


def test_oidn_alone_fails_the_whole_image_guard(dev_runs):
    failures = whole_image_failures({name: run.oidn for name, run in dev_runs.items()}, dev_runs)
    assert [f.split(":")[0] for f in failures][:2] == ["pooled", "crops"], failures   # ratio 1, no crop beaten


def untrained_whole_image_failures(shipped: Networks, seed: int, runs: dict[str, DevRun]) -> list[str]:
    """The whole-image guard's failures for an untrained denoiser of this seed, on the runs' own samples."""
    return whole_image_failures(untrained_images(shipped, seed, runs), runs)


def test_an_untrained_denoiser_of_the_shipped_architecture_fails_the_whole_image_guard(shipped, dev_runs):
    # One seed in the default suite: over seeds 0-2 the untrained figures spread by 0.002 (pooled
    # 0.8366-0.8383) and 0.014 (crops won 0.606-0.620), seed 0's margins to the bars (0.831, 0.68)
    # 0.0061 and 0.069; on the shipped run's own samples they no longer move between runs (they
    # did by 0.005 when each scene was rendered again); the other seeds run in the slow test below.
    failures = untrained_whole_image_failures(shipped, UNTRAINED_SEEDS[0], dev_runs)
    assert [f.split(":")[0] for f in failures][:2] == ["pooled", "crops"], failures


@pytest.mark.slow
def test_untrained_denoisers_of_other_seeds_fail_the_whole_image_guard_too(shipped, dev_runs):
    for seed in UNTRAINED_SEEDS[1:]:
        failures = untrained_whole_image_failures(shipped, seed, dev_runs)
        assert [f.split(":")[0] for f in failures][:2] == ["pooled", "crops"], (seed, failures)


# --- the kernels alone ------------------------------------------------------------------------------

def kernel_smape_cut(denoiser: Denoiser, record, reference) -> float:
    """The SMAPE cut of the kernels alone: every level's result before the candidate joins."""
    frame = frame_tensors(record.buffers[0])
    with torch.inference_mode():
        cache = prepare_frame(denoiser, [frame], 0).cache
        kernel_levels: list[torch.Tensor] = []
        denoiser.filter_levels(cache, 1.0, kernel_levels)
        kernels = to_image(denoiser.merge_levels(cache, kernel_levels))
    return smape(record.buffers[0].mean, reference) / smape(kernels, reference)


@pytest.mark.parametrize("name", SCENES)
def test_shipped_kernels_keep_their_smape_cut_on_an_unseen_scene(shipped, dev_runs, name):
    run = dev_runs[name]
    assert kernel_smape_cut(shipped.denoiser, run.record, run.reference) >= GUARDS[name].kernel_smape_cut


@pytest.mark.parametrize("name", SCENES)
def test_untrained_kernels_fail_the_kernel_guard(shipped, tiny_networks, dev_runs, name):
    run = dev_runs[name]
    for denoiser in (tiny_networks.denoiser, untrained_shipped_architecture(shipped, 0).denoiser):
        # the loop's first iteration is uniform and seeded: the shipped run's render is this one's
        assert kernel_smape_cut(denoiser, run.record, run.reference) < GUARDS[name].kernel_smape_cut


# --- the error network ------------------------------------------------------------------------------

def true_error(denoised: np.ndarray, reference: np.ndarray) -> np.ndarray:
    return np.abs(denoised - reference).mean(axis=2) / (np.abs(reference).mean(axis=2) + 1e-2)


def rank_against_true_error(error_map: np.ndarray, run: DevRun) -> float:
    return spearman(error_map.ravel(), true_error(run.record.denoised[0], run.reference).ravel())


def sqrt_variance_maps(run: DevRun) -> dict[str, np.ndarray]:
    """The plain estimate an error network must beat: the noisy mean's standard deviation over the
    denoised radiance, formed five ways (channel mean or max, ε or none)."""
    std, denoised = np.sqrt(np.maximum(run.record.buffers[0].variance, 0.0)), np.abs(run.record.denoised[0])
    return {"mean σ ÷ (mean d + 1e-2)": std.mean(2) / (denoised.mean(2) + 1e-2),
            "mean σ ÷ (mean d + 1e-3)": std.mean(2) / (denoised.mean(2) + 1e-3),
            "mean σ ÷ mean d": std.mean(2) / np.maximum(denoised.mean(2), 1e-8),
            "mean of σ ÷ (d + 1e-2)": (std / (denoised + 1e-2)).mean(2),
            "max of σ ÷ (d + 1e-2)": (std / (denoised + 1e-2)).max(2)}


@pytest.mark.parametrize("name", SCENES)
def test_shipped_error_network_ranks_pixels_by_their_true_error(dev_runs, name):
    run = dev_runs[name]
    assert rank_against_true_error(run.record.error[0], run) >= GUARDS[name].error_rank


@pytest.mark.parametrize("name", SCENES)
def test_a_sqrt_variance_map_fails_the_error_ranking_guard(dev_runs, name):
    run = dev_runs[name]
    for how, error_map in sqrt_variance_maps(run).items():
        assert rank_against_true_error(error_map, run) < GUARDS[name].error_rank, how


@pytest.mark.parametrize("name", SCENES)
def test_an_untrained_error_network_fails_the_error_ranking_guard(shipped, dev_runs, name):
    torch.manual_seed(0)
    untrained = Networks(shipped.denoiser, ErrorPredictor(shipped.error_predictor.config).eval())
    loop = loop_on_samples(dev_runs[name], untrained)
    image, error = loop.denoised()[0], loop.state.error_maps[0]   # its map moves the final image's fallback
    rank = spearman(error.ravel(), true_error(image, dev_runs[name].reference).ravel())
    assert rank < GUARDS[name].error_rank


# --- no-regression checks ---------------------------------------------------------------------------

def test_shipped_denoiser_keeps_the_hard_shadows_contrast(dev_runs):
    run = dev_runs["hard_shadows"]
    contrast = shadow_contrast_ratio(run.record.denoised[0], run.reference, SHADOW_REGIONS["hard_shadows"])
    assert contrast >= MIN_SHADOW_CONTRAST


def denoise_buffer(denoiser, buffer, lam: float = 1.0) -> np.ndarray:
    frame = frame_tensors(buffer)
    with torch.inference_mode():
        return to_image(denoise_frame(denoiser, [frame], 0, lam))


def luminance(image: np.ndarray) -> np.ndarray:
    return image @ np.array([0.2126, 0.7152, 0.0722])


def firefly_positions(shape: tuple[int, int]) -> list[tuple[int, int]]:
    """Six seeded pixels at least 20 px from the border."""
    rng = np.random.default_rng(0)
    return [(int(rng.integers(20, shape[0] - 20)), int(rng.integers(20, shape[1] - 20))) for _ in range(6)]


def with_firefly(buffer, y: int, x: int):
    """A copy of the buffer with one sample FIREFLY_FACTOR× the pixel's luminance (at least 0.05)
    added at (y, x): a real 16-spp render with one heavy-tailed sample."""
    injected = copy.deepcopy(buffer)
    value = FIREFLY_FACTOR * max(float(luminance(buffer.mean[y, x])), 0.05) * injected.spp[y, x]
    injected.radiance_sum[y, x] += value
    injected.radiance_sq_sum[y, x] += value * value
    return injected


def firefly_buffers(buffer) -> Iterator:
    """The render itself, then a copy with one firefly at each of firefly_positions."""
    yield buffer
    for y, x in firefly_positions(buffer.shape):
        yield with_firefly(buffer, y, x)


@pytest.fixture(scope="module")
def shipped_firefly_images(shipped, dev_runs) -> dict[float, list[np.ndarray]]:
    """λ → the shipped denoiser's images of firefly_buffers(hard_shadows' render), λ = 1 and
    DETAIL_LAMBDA from one prepare each (the λ tail is the cheap part)."""
    images: dict[float, list[np.ndarray]] = {1.0: [], DETAIL_LAMBDA: []}
    for buffer in firefly_buffers(dev_runs["hard_shadows"].record.buffers[0]):
        with torch.inference_mode():
            cache = prepare_frame(shipped.denoiser, [frame_tensors(buffer)], 0).cache
            for lam, found in images.items():
                found.append(to_image(shipped.denoiser.apply(cache, lam)))
    return images


def test_a_firefly_leaves_no_dark_halo_around_it(shipped_firefly_images, dev_runs):
    # The yardstick is the same denoiser on the same render without the firefly, so only the
    # firefly's own effect is measured (the "no halo darker than the surrounding reference").
    without, *with_one_each = (luminance(image) for image in shipped_firefly_images[1.0])
    positions = firefly_positions(dev_runs["hard_shadows"].record.buffers[0].shape)
    for (y, x), with_one in zip(positions, with_one_each):
        ys, xs = np.mgrid[y - FIREFLY_WINDOW:y + FIREFLY_WINDOW + 1, x - FIREFLY_WINDOW:x + FIREFLY_WINDOW + 1]
        distance = np.maximum(np.abs(ys - y), np.abs(xs - x))
        for ring in range(1, FIREFLY_WINDOW + 1):
            inside = distance == ring
            share = with_one[ys[inside], xs[inside]].mean() / without[ys[inside], xs[inside]].mean()
            assert share >= MIN_RING_SHARE_AROUND_A_FIREFLY, (y, x, ring, share)


# --- λ = 10: the shadow-edge and firefly guards -----------------------------------------------------

Denoise = Callable[[object], np.ndarray]   # a frame buffer → its denoised (H, W, 3) image


def at_detail_lambda(denoiser: Denoiser) -> Denoise:
    return lambda buffer: denoise_buffer(denoiser, buffer, DETAIL_LAMBDA)


def oidn_alone(buffer) -> np.ndarray:
    """The planted variant: the candidate passed straight through (OIDN has no λ)."""
    return oidn_image(buffer.mean, buffer.albedo, buffer.normal)


def edge_band(shadow: np.ndarray) -> np.ndarray:
    """Pixels with a 4-neighbour in the other class: both sides of every shadow boundary, where
    a blur mixes the classes first (the whole region's class means hide it: a 1-px blur there
    moves them by a few per cent)."""
    padded = np.pad(shadow, 1, mode="edge")
    centre = padded[1:-1, 1:-1]
    return ((centre != padded[:-2, 1:-1]) | (centre != padded[2:, 1:-1])
            | (centre != padded[1:-1, :-2]) | (centre != padded[1:-1, 2:]))


def shadow_edge_contrast(image: np.ndarray, reference: np.ndarray) -> float:
    """bench.quality_measures.shadow_contrast_ratio's (lit − shadow)/(lit + shadow) on hard_shadows'
    SHADOW_REGIONS, the class means taken over the edge band only, ÷ the reference's."""
    h, w = reference.shape[:2]
    top, bottom, left, right = SHADOW_REGIONS["hard_shadows"]
    window = (slice(int(top * h), int(bottom * h)), slice(int(left * w), int(right * w)))
    ref, img = luminance(reference[window]), luminance(np.nan_to_num(image[window]))
    shadow = ref < 0.5 * (np.percentile(ref, 5) + np.percentile(ref, 95))
    lit, dark = ~shadow & edge_band(shadow), shadow & edge_band(shadow)

    def contrast(values: np.ndarray) -> float:
        return (values[lit].mean() - values[dark].mean()) / max(values[lit].mean() + values[dark].mean(), 1e-12)

    return float(contrast(img) / contrast(ref))


def shadow_edge_contrast_to_oidn(denoise: Denoise, run: DevRun) -> float:
    buffer = run.record.buffers[0]
    return shadow_edge_contrast(denoise(buffer), run.reference) / shadow_edge_contrast(run.oidn, run.reference)


def firefly_window_growth(images: Iterable[np.ndarray], run: DevRun) -> Iterator[float]:
    """Per firefly position: the mean SMAPE of its (2·FIREFLY_WINDOW + 1)² window with the firefly
    ÷ without it; `images` the same denoiser's of firefly_buffers (lazily: a planted variant fails early)."""
    images = iter(images)
    without = true_error_map(next(images), run.reference)
    for (y, x), image in zip(firefly_positions(run.reference.shape[:2]), images):
        window = (slice(y - FIREFLY_WINDOW, y + FIREFLY_WINDOW + 1), slice(x - FIREFLY_WINDOW, x + FIREFLY_WINDOW + 1))
        yield float(true_error_map(image, run.reference)[window].mean() / without[window].mean())


def denoised_fireflies(denoise: Denoise, run: DevRun) -> Iterator[np.ndarray]:
    return (denoise(buffer) for buffer in firefly_buffers(run.record.buffers[0]))


def test_shipped_denoiser_at_lambda_10_keeps_sharper_shadow_edges_than_oidn(shipped, dev_runs):
    ratio = shadow_edge_contrast_to_oidn(at_detail_lambda(shipped.denoiser), dev_runs["hard_shadows"])
    assert ratio >= MIN_SHADOW_EDGE_CONTRAST_TO_OIDN


def test_oidn_alone_and_an_untrained_denoiser_fail_the_shadow_edge_guard(shipped, dev_runs):
    run = dev_runs["hard_shadows"]
    for label, denoise in (("OIDN alone", oidn_alone),
                           ("untrained", at_detail_lambda(untrained_shipped_architecture(shipped, 0).denoiser))):
        assert shadow_edge_contrast_to_oidn(denoise, run) < MIN_SHADOW_EDGE_CONTRAST_TO_OIDN, label


def test_shipped_denoiser_at_lambda_10_keeps_a_firefly_on_its_pixel(shipped_firefly_images, dev_runs):
    growth = list(firefly_window_growth(shipped_firefly_images[DETAIL_LAMBDA], dev_runs["hard_shadows"]))
    assert max(growth) <= MAX_FIREFLY_WINDOW_SMAPE_GROWTH, growth


def test_oidn_alone_and_an_untrained_denoiser_fail_the_firefly_guard(shipped, dev_runs):
    run = dev_runs["hard_shadows"]
    for label, denoise in (("OIDN alone", oidn_alone),
                           ("untrained", at_detail_lambda(untrained_shipped_architecture(shipped, 0).denoiser))):
        growth = firefly_window_growth(denoised_fireflies(denoise, run), run)
        assert any(g > MAX_FIREFLY_WINDOW_SMAPE_GROWTH for g in growth), label


def lambda_figures(label: str, denoise: Denoise, run: DevRun) -> str:
    growth = ", ".join(f"{g:.2f}" for g in firefly_window_growth(denoised_fireflies(denoise, run), run))
    contrast = shadow_edge_contrast_to_oidn(denoise, run)
    return f"{label}: shadow edge contrast ÷ OIDN's {contrast:.4f}; firefly window SMAPE × {growth}"


def main(seed: int = 0) -> None:
    """Print the figures the bars above were set from: `python tests/loop/test_shipped_networks.py [SEED]`
    (SEED: the loop's; the untrained networks' seeds are UNTRAINED_SEEDS)."""
    torch.set_num_threads(1)
    shipped = load_networks()
    runs = render_dev_runs(shipped, SCENES, seed)
    images = {"shipped": {name: run.record.denoised[0] for name, run in runs.items()},
              "OIDN alone": {name: run.oidn for name, run in runs.items()}}
    images |= {f"untrained seed {s}": untrained_images(shipped, s, runs) for s in UNTRAINED_SEEDS}
    for label, denoised in images.items():
        figures = whole_image_figures(denoised, runs)
        scenes = ", ".join(f"{name} {ratio:.4f}" for name, ratio in figures.scene_ratios.items())
        print(f"{label}: crops' SMAPE ÷ OIDN's {figures.pooled:.4f}, crops won {figures.crops_won:.3f}; {scenes}")
    untrained = untrained_shipped_architecture(shipped, 0).denoiser
    for name, run in runs.items():
        maps = ", ".join(f"[{how}] {rank_against_true_error(m, run):.3f}" for how, m in sqrt_variance_maps(run).items())
        print(f"{name}: kernel cut {kernel_smape_cut(shipped.denoiser, run.record, run.reference):.2f} (untrained "
              f"seed 0 {kernel_smape_cut(untrained, run.record, run.reference):.2f}), error rank "
              f"{rank_against_true_error(run.record.error[0], run):.3f}; √variance maps {maps}")
    run = runs["hard_shadows"]
    contrast = {label: shadow_contrast_ratio(image, run.reference, SHADOW_REGIONS["hard_shadows"])
                for label, image in (("shipped", run.record.denoised[0]), ("OIDN", run.oidn))}
    print(f"hard_shadows at λ = 1: contrast shipped {contrast['shipped']:.4f}, OIDN {contrast['OIDN']:.4f}")
    denoisers = {"shipped": at_detail_lambda(shipped.denoiser), "OIDN alone": oidn_alone}
    denoisers |= {f"untrained seed {s}": at_detail_lambda(untrained_shipped_architecture(shipped, s).denoiser)
                  for s in UNTRAINED_SEEDS}
    print(f"hard_shadows at λ = {DETAIL_LAMBDA:g}:\n" + "\n".join(lambda_figures(f"  {label}", denoise, run)
                                                           for label, denoise in denoisers.items()))


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 0)
