"""bench/experiments: a variant's setting (the allocator's, the gate offsets) must act only
where it is measured, or it would leak into the next measurement (and into the product)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

import service.loop.allocate as allocate
import service.loop.loop as loop
from bench.common import denoise_and_predict, denoiser_settings, image_metrics
from bench.experiments.allocation_bound import best_allocation_ratio, fitted_exponent, optimal_counts, scene_bounds
from bench.experiments.allocation_variants import allocator_variant, equal_gain_samples
from bench.experiments.change_map import ChangeShapedLoop, change_shaped
from bench.experiments.disagreement_map import ModulatedErrorMap, modulate
from bench.experiments.error_ceiling import (infinite_render_estimate, leave_one_out_spearman, pairwise_spearman,
                                             ranking_row)
from bench.experiments.energy_tolerance import UNTOUCHED, outputs_per_tolerance
from bench.experiments.gate_bound import kernels_and_candidate
from bench.experiments.gate_offset import offset_ratios
from bench.experiments.sample_cost import scene_cost, spread_over
from bench.experiments.seed_spread import paired_ratio
from bench.experiments.setting_sweep import parse_values, setting_images, summary_rows
from bench.experiments.target_cost import INPUT_SPP, scene_costs
from bench.experiments.trunk_speed import median_seconds, random_frame
from models.denoiser import Denoiser, DenoiserConfig
from models.error_predictor import ErrorPredictor, ErrorPredictorConfig
from models.frames import FrameTensors
from models.kernel_disagreement import kernel_disagreement
from service.loop.loop import RenderLoop
from service.loop.oidn import candidate_for
from service.loop.spec import LoopSpec
from service.loop.tensors import to_image


def test_allocator_variant_applies_its_settings_inside_and_restores_the_product_after():
    weights = np.random.default_rng(0).uniform(0.1, 1.0, (8, 8))
    overrides = {"clamp_percentile": 50.0, "dilate_radius": 0, "floor_fraction": 0.0}
    product = (allocate.error_weights, loop.allocate_samples)
    default = allocate.allocate_samples(weights, 1000, seed=0)
    with allocator_variant(2.0, overrides):
        np.testing.assert_allclose(allocate.error_weights(weights), weights ** 2)
        varied = loop.allocate_samples(weights, 1000, seed=0)
        np.testing.assert_array_equal(varied, allocate.allocate_samples(weights, 1000, seed=0, **overrides))
        assert not np.array_equal(varied, default)
    assert (allocate.error_weights, loop.allocate_samples) == product
    np.testing.assert_array_equal(loop.allocate_samples(weights, 1000, seed=0), default)


def test_equal_gain_spends_the_budget_where_one_more_sample_removes_most_error():
    error = np.array([[0.2, 0.2, 0.05, 0.0]])
    spp = np.array([[16, 64, 16, 16]])
    new = equal_gain_samples(error, spp, 128, beta=0.5)
    assert new.sum() == pytest.approx(128) and (new >= 0).all()
    assert new[0, 3] == 0                     # nothing to gain where there is no error
    assert new[0, 0] > new[0, 1] > 0          # equal error: the pixel with fewer samples gains more
    assert new[0, 0] > new[0, 2]              # equal samples: the larger error gains more


def test_equal_gain_totals_follow_the_lagrange_optimum_when_every_pixel_gets_samples():
    """With e ∝ n^−β the optimum total is n ∝ (e·n^β)^(1/(1+β)): at equal counts ∝ e^(2/3) for β = ½."""
    error = np.array([[0.01, 0.08, 0.27]])
    spp = np.full((1, 3), 4)
    new = equal_gain_samples(error, spp, 3000, beta=0.5)
    totals = new + spp
    np.testing.assert_allclose(totals / totals.sum(), error ** (2 / 3) / (error ** (2 / 3)).sum(), rtol=1e-6)


def test_equal_gain_without_any_error_or_budget_stays_finite_and_uniform():
    np.testing.assert_allclose(equal_gain_samples(np.zeros((2, 2)), np.full((2, 2), 8), 8, 0.5), 2.0)
    assert (equal_gain_samples(np.full((2, 2), np.nan), np.zeros((2, 2)), 0, 0.5) == 0).all()



def test_equal_gain_variant_replaces_the_error_allocators_counts_for_one_loop_only():
    product = loop.next_counts
    with allocator_variant(1.0, {}, gain=0.5):
        assert loop.next_counts is not product
    assert loop.next_counts is product


def test_allocation_bound_is_one_when_the_error_is_the_same_everywhere():
    assert best_allocation_ratio(np.full((8, 8), 0.01), 0.3) == pytest.approx(1.0)
    assert best_allocation_ratio(np.zeros((4, 4)), 0.3) == 1.0


def test_allocation_bound_sends_every_added_sample_to_the_half_that_has_error():
    """Half the frame error-free: the other half gets 16 + 2·112 = 240 spp, so its error falls by
    (128/240)^β and the frame's with it."""
    error = np.zeros((8, 8))
    error[:, :4] = 0.02
    assert best_allocation_ratio(error, 0.25) == pytest.approx((128 / 240) ** 0.25, rel=1e-6)


def test_optimal_counts_keep_the_mean_and_equalise_the_marginal_gains_of_the_pixels_they_feed():
    rng = np.random.default_rng(3)
    v, beta = rng.uniform(0.0, 1.0, 500), rng.uniform(0.1, 0.6, 500)
    n = optimal_counts(v, beta, 16, 128)
    assert n.mean() == pytest.approx(128, rel=1e-9) and n.min() >= 16
    fed = n > 16 * (1 + 1e-9)
    gains = beta[fed] * v[fed] * n[fed] ** (-beta[fed] - 1)
    np.testing.assert_allclose(gains, gains[0], rtol=1e-6)
    assert (beta[~fed] * v[~fed] * 16.0 ** (-beta[~fed] - 1) <= gains[0] * (1 + 1e-6)).all()


def test_fitted_exponent_recovers_a_power_law_and_the_scene_bounds_read_it():
    rng = np.random.default_rng(4)
    expected_16 = rng.uniform(0.01, 0.05, (32, 32))
    expected_128 = expected_16 * 8.0 ** -0.3
    assert fitted_exponent(expected_16, expected_128) == pytest.approx(np.full((32, 32), 0.3))
    bounds = scene_bounds(expected_16, expected_128)
    assert bounds["beta"] == pytest.approx(0.3)
    assert 0.0 < bounds["pixel"] < bounds["shared 5×5"] < 1.0   # blurring the map leaves less to aim at
    assert 0.0 < bounds["tiles, own β"] < 1.0


@torch.no_grad()
def test_gate_offset_sweep_scores_each_setting_and_leaves_the_denoisers_config_as_it_was():
    config = DenoiserConfig(width=8, spatial_blocks=1, temporal=False, oidn_candidate=True)
    denoiser = Denoiser(config).eval()
    g = torch.Generator().manual_seed(0)
    frame = FrameTensors(color=torch.rand(1, 3, 16, 16, generator=g), variance=torch.rand(1, 3, 16, 16, generator=g) * 0.1,
                         albedo=torch.full((1, 3, 16, 16), 0.5), normal=torch.rand(1, 3, 16, 16, generator=g),
                         depth=torch.ones(1, 1, 16, 16), motion=None)
    candidate = torch.rand(1, 3, 16, 16, generator=g)
    reference = to_image(candidate) * 1.1
    oidn = image_metrics(to_image(candidate), reference)
    settings = [(0.0, 0.0, False, None), (10.0, 10.0, False, None), (0.0, 0.0, True, None), (0.0, 0.0, False, 0.0)]
    ratios = offset_ratios(denoiser, frame, candidate, reference, oidn, settings)
    assert denoiser.config == config
    assert len(ratios) == 4 and ratios[0] != ratios[1] and ratios[0] != ratios[2]
    np.testing.assert_allclose(ratios[3], (1.0, 1.0), rtol=1e-4)   # a zero-width clamp: the kernels become OIDN
    np.testing.assert_allclose(ratios[1], (1.0, 1.0), rtol=0.05)   # b = 10 everywhere: OIDN's image back


def test_energy_tolerance_sweep_pulls_towards_the_samples_only_as_tau_grows_and_restores_the_config():
    # gate offset 10: the output is the candidate's image, whatever the untrained kernels do
    config = DenoiserConfig(width=8, spatial_blocks=1, temporal=False, oidn_candidate=True, energy_tolerance=0.03,
                            gate_offset=10.0)
    torch.manual_seed(0)
    denoiser = Denoiser(config).eval()
    g = torch.Generator().manual_seed(0)
    color = torch.rand(1, 3, 16, 16, generator=g)
    frame = FrameTensors(color=color, variance=torch.full((1, 3, 16, 16), 1e-8), albedo=torch.full((1, 3, 16, 16), 0.5),
                         normal=torch.rand(1, 3, 16, 16, generator=g), depth=torch.ones(1, 1, 16, 16), motion=None)
    candidate = color * 0.8                       # a denoiser that lost a fifth of the energy
    with torch.no_grad():
        cache = denoiser.prepare([frame], 0, candidate)
        untouched, pulled = outputs_per_tolerance(denoiser, cache, [UNTOUCHED, 1.0])
    assert denoiser.config == config
    samples_mean = float(color.mean())
    assert untouched.mean() == pytest.approx(0.8 * samples_mean, rel=0.02)  # left as the network made it
    assert pulled.mean() == pytest.approx(samples_mean, rel=1e-3)         # rse ≪ τ: the samples' total


def test_energy_blocks_sweep_restores_each_half_where_it_was_lost_and_restores_the_config():
    # gate offset 10: the output is the candidate's image; the candidate lost a fifth on its left half only
    config = DenoiserConfig(width=8, spatial_blocks=1, temporal=False, oidn_candidate=True, energy_tolerance=0.03,
                            gate_offset=10.0)
    torch.manual_seed(0)
    denoiser = Denoiser(config).eval()
    color = torch.ones(1, 3, 32, 32)
    frame = FrameTensors(color=color, variance=torch.full((1, 3, 32, 32), 1e-10), albedo=torch.full((1, 3, 32, 32), 0.5),
                         normal=torch.zeros(1, 3, 32, 32), depth=torch.ones(1, 1, 32, 32), motion=None)
    candidate = color.clone()
    candidate[..., :16] *= 0.8
    with torch.no_grad():
        image_wide, blocks = setting_images(denoiser, frame, candidate, "energy_block", [0, 8])
    assert denoiser.config == config
    assert image_wide[:, 24:].mean() > 1.05                               # one factor: the right half overshoots
    np.testing.assert_allclose(blocks[:, 24:], 1.0, rtol=0.01)            # block by block: both halves right
    np.testing.assert_allclose(blocks[:, :8], 1.0, rtol=0.01)


def test_denoiser_settings_apply_inside_and_are_undone_even_when_the_measurement_fails():
    denoiser = Denoiser(DenoiserConfig(width=8, spatial_blocks=1, temporal=False, oidn_candidate=True)).eval()
    config = denoiser.config
    with pytest.raises(RuntimeError):
        with denoiser_settings(denoiser, gate_offset=3.0, kernel_clamp=0.5):
            assert (denoiser.config.gate_offset, denoiser.config.kernel_clamp) == (3.0, 0.5)
            raise RuntimeError("a measurement failed")
    assert denoiser.config == config


def test_error_ceiling_is_one_for_a_repeatable_map_and_near_zero_for_pure_noise():
    rng = np.random.default_rng(0)
    same = np.repeat(rng.random((1, 32, 32)), 4, axis=0)
    assert leave_one_out_spearman(same) == pytest.approx(1.0)
    assert pairwise_spearman(same, block=8) == pytest.approx(1.0)
    noise = rng.random((4, 32, 32))
    assert abs(leave_one_out_spearman(noise)) < 0.1 and abs(pairwise_spearman(noise)) < 0.1


def test_error_ceilings_many_render_estimate_agrees_with_averaging_many_renders():
    """map = expected + noise of equal variance: two maps correlate ≈ 0.5, the expected map with
    one ≈ 0.71; the mean of 59 others reaches nearly that, and √(two) estimates it from two."""
    rng = np.random.default_rng(1)
    maps = rng.normal(size=(1, 64, 64)) + rng.normal(size=(60, 64, 64))
    two = pairwise_spearman(maps)
    assert 0.44 < two < 0.54
    assert infinite_render_estimate(two) == pytest.approx(leave_one_out_spearman(maps), abs=0.03)


def test_error_ceiling_scores_a_predictor_against_its_own_render_and_the_repeatable_part():
    rng = np.random.default_rng(2)
    expected = rng.random((1, 32, 32))
    true = expected + 0.3 * rng.random((6, 32, 32))
    row = ranking_row(true, np.repeat(expected, 6, axis=0))
    assert row["network_vs_repeatable"] > row["network"] > 0.5   # the oracle ranks the repeatable part best
    assert row["repeatable"] == pytest.approx(leave_one_out_spearman(true))


def test_target_cost_times_the_inputs_sample_count_the_build_renders_and_every_count_asked():
    assert INPUT_SPP == 176   # spp16 → spp128 uniformly (128), then adaptive32 (+16) and adaptive64 (+32)
    costs = scene_costs(scenes=1, size=8, spp_counts=(1, 4))
    assert set(costs) == {1, 4} and all(seconds > 0 for seconds in costs.values())


def test_spread_over_puts_exactly_the_total_on_the_masked_pixels_as_evenly_as_it_can():
    mask = np.zeros((4, 5), bool)
    mask[1:3, 1:4] = True
    counts = spread_over(mask, 20)
    assert counts.sum() == 20 and (counts[~mask] == 0).all()
    assert set(np.unique(counts[mask])) == {3, 4}
    assert spread_over(mask, 0).sum() == 0
    with pytest.raises(ValueError, match="no pixel"):
        spread_over(np.zeros((2, 2), bool), 5)


def test_sample_cost_times_a_scene_whose_object_leaves_background_to_miss(tmp_path):
    scene = tmp_path / "ball.xml"
    scene.write_text("""<scene version="3.0.0">
  <integrator type="path"/>
  <sensor type="perspective"><float name="fov" value="40"/>
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/></film>
  </sensor>
  <shape type="sphere"><float name="radius" value="0.5"/></shape>
  <emitter type="point"><point name="position" value="0, 2, 3"/><rgb name="intensity" value="10"/></emitter>
</scene>""")
    row = scene_cost(str(scene), spp=2, repeats=1)
    assert 0.0 < row["hit_fraction"] < 0.5   # the ball covers the centre, the rest is missed
    assert all(row[key] > 0 for key in ("uniform", "hit", "miss"))


def test_trunk_speed_times_both_trunks_on_the_same_frame():
    frame = random_frame(16)
    for trunk in ("levels", "unet"):
        assert median_seconds(DenoiserConfig(width=4, temporal=False, trunk=trunk), frame, repeats=1) > 0


def test_modulation_moves_the_ranking_but_keeps_the_mean_prediction():
    predicted = torch.full((1, 1, 4, 4), 0.02)
    dis = torch.linspace(0.01, 0.3, 16).reshape(1, 1, 4, 4)
    for gamma in (0.25, 1.0):
        out = modulate(predicted, dis, gamma)
        torch.testing.assert_close(out.mean(), predicted.mean())
        assert bool((out.flatten().diff() > 0).all())   # more disagreement, more predicted error
    assert modulate(predicted, dis, 0.0) is predicted


def test_the_modulated_error_map_at_gamma_0_is_the_error_network_itself():
    class Constant(torch.nn.Module):
        def forward(self, frame, denoised):
            return torch.full_like(denoised[:, :1], 0.03)

    denoised = torch.rand(1, 3, 8, 8)
    out = ModulatedErrorMap(Constant(), Denoiser(DenoiserConfig(width=8)), 0.0)(None, denoised)
    torch.testing.assert_close(out, torch.full((1, 1, 8, 8), 0.03))


@torch.no_grad()
def test_kernels_and_candidate_returns_the_shipped_output_its_kernels_and_oidns_image():
    denoiser = Denoiser(DenoiserConfig(width=8, spatial_blocks=1, temporal=False, oidn_candidate=True)).eval()
    frame = random_frame(16)
    output, kernels, candidate = kernels_and_candidate(denoiser, frame)
    torch.testing.assert_close(candidate, candidate_for(denoiser, frame))
    torch.testing.assert_close(output, denoiser([frame], 0, 1.0, candidate))
    assert kernels.shape == output.shape and not torch.equal(kernels, candidate)


@torch.no_grad()
def test_denoise_and_predict_hands_a_disagreement_reading_network_what_the_loop_gives_it():
    denoiser = Denoiser(DenoiserConfig(width=8, spatial_blocks=1, temporal=False, oidn_candidate=True)).eval()
    reader = ErrorPredictor(ErrorPredictorConfig(width=4, blocks=1, disagreement_input=True)).eval()
    plain = ErrorPredictor(ErrorPredictorConfig(width=4, blocks=1)).eval()
    frame = random_frame(16)
    output, kernels, candidate = kernels_and_candidate(denoiser, frame)
    cache, denoised, error = denoise_and_predict(denoiser, reader, [frame], 0)
    torch.testing.assert_close(denoised, output)
    torch.testing.assert_close(denoiser.apply(cache, 1.0), output)   # the cache serves further λ tails
    torch.testing.assert_close(error, reader(frame, output, kernel_disagreement(kernels, candidate)))
    torch.testing.assert_close(denoise_and_predict(denoiser, plain, [frame], 0)[2], plain(frame, output))
    modulated = ModulatedErrorMap(reader, denoiser, 0.0)(frame, output)   # γ = 0: the network's own map
    torch.testing.assert_close(modulated, reader(frame, output, kernel_disagreement(kernels, candidate)))


def test_paired_ratio_settles_a_consistent_lead_and_calls_a_seed_to_seed_swing_a_tie():
    consistent = paired_ratio([0.98, 0.97, 0.99, 0.98], [1.0, 1.0, 1.0, 1.0])
    assert consistent.verdict == "ours" and consistent.wins == 4 and consistent.geometric_mean == pytest.approx(0.98, abs=0.002)
    assert (consistent.low, consistent.high) == pytest.approx((0.97, 0.99))
    swinging = paired_ratio([0.95, 1.05, 0.96, 1.04], [1.0, 1.0, 1.0, 1.0])
    assert swinging.verdict == "tie" and swinging.wins == 2
    behind = paired_ratio([1.03, 1.02, 1.04], [1.0, 1.0, 1.0])
    assert behind.verdict == "OIDN" and behind.t > 2 and behind.wins == 0
    assert paired_ratio([1.0, 1.0], [1.0, 1.0]).t == 0.0           # identical: no spread, no verdict


def test_setting_sweep_reads_each_value_as_the_settings_own_type():
    assert parse_values("albedo_floor", ["0", "0.1"]) == [0.0, 0.1]
    assert all(type(v) is float for v in parse_values("albedo_floor", ["0", "0.1"]))
    assert parse_values("energy_block", ["0", "32"]) == [0, 32]
    assert all(type(v) is int for v in parse_values("energy_block", ["32"]))
    assert parse_values("kernel_clamp", ["off", "0.5"]) == [None, 0.5]
    assert parse_values("candidate_cap", ["on", "off"]) == [True, False]
    with pytest.raises(ValueError):
        parse_values("energy_block", ["0.5"])


def test_setting_sweep_summary_takes_medians_counts_and_their_mean_per_value():
    # two scenes at one spp; value 1 is at most OIDN's on one scene in SMAPE and both in relMSE
    cells = {(16, 0): [(1.2, 1.1), (1.0, 0.9)], (16, 1): [(0.9, 0.8), (1.1, 0.7)]}
    rows = summary_rows(cells, [16], [0, 1])
    assert rows[0] == (0, [(1.1, 1, 1.0, 1)], pytest.approx(1.05))
    assert rows[1] == (1, [(1.0, 1, 0.75, 2)], pytest.approx(0.875))


def test_setting_sweep_images_follow_the_setting_and_restore_the_config():
    config = DenoiserConfig(width=8, spatial_blocks=1, temporal=False, oidn_candidate=True)
    torch.manual_seed(0)
    denoiser = Denoiser(config).eval()
    albedo = torch.full((1, 3, 16, 16), 0.8)
    albedo[..., :8] = 0.0
    color = torch.where(albedo > 0, 0.8, 1.0)
    frame = FrameTensors(color=color, variance=torch.full_like(color, 1e-4), albedo=albedo,
                         normal=torch.zeros(1, 3, 16, 16), depth=torch.ones(1, 1, 16, 16), motion=None)
    with torch.no_grad():
        plain, floored, plain_again = setting_images(denoiser, frame, color.clone(), "albedo_floor", [0.0, 0.1, 0.0])
    assert denoiser.config == config
    np.testing.assert_array_equal(plain, plain_again)
    assert np.abs(plain - floored).max() > 1e-3


def test_change_shaping_keeps_the_maps_mean_and_ranks_by_how_far_each_pixel_moved():
    error = np.full((12, 12), 0.02, np.float32)
    previous = np.full((12, 12, 3), 0.5, np.float32)
    current = previous.copy()
    current[:, 6:] = 0.7                                     # the right half moved, the left did not
    for gamma in (0.25, 1.0):
        shaped = change_shaped(error, previous, current, gamma)
        assert shaped.mean() == pytest.approx(error.mean(), rel=1e-5)
        assert shaped[:, 9:].min() > shaped[:, :3].max()
    np.testing.assert_array_equal(change_shaped(error, previous, current, 0.0), error)
    assert change_shaped(error, previous, previous, 1.0) is error   # no change measured: the map as it was


def test_the_change_shaped_loop_reshapes_the_map_only_once_it_has_an_image_to_compare(tiny_networks):
    spec = LoopSpec(scene="cornell-box", width=16, height=16, max_iterations=2, allocator="error", seed=3)
    (first, second), (shaped_first, shaped_second) = (
        [(r.buffers[0].spp.copy(), r.error[0].copy(), r.denoised[0].copy()) for r in loop.run()]
        for loop in (RenderLoop(spec, tiny_networks), ChangeShapedLoop(spec, tiny_networks, 0.5)))
    np.testing.assert_array_equal(first[1], shaped_first[1])            # iteration 0: nothing to compare
    np.testing.assert_array_equal(second[0], shaped_second[0])          # so the same samples followed
    assert shaped_second[1].mean() == pytest.approx(second[1].mean(), rel=1e-4)
    np.testing.assert_allclose(shaped_second[1], change_shaped(second[1], first[2], second[2], 0.5), rtol=1e-5, atol=1e-9)
    assert not np.allclose(shaped_second[1], second[1])
