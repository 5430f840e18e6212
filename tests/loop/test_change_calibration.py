"""The error map's mean calibrated by how far the denoised image moved since the previous
iteration (service.loop.change_calibration), in the function and in a real loop."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from models.error_predictor import ErrorPredictor, ErrorPredictorConfig
from models.pretrained import Networks
from tests.models.conftest import PLAIN_ERROR_NETWORK
from service.loop.change_calibration import calibrate_by_change, calibrated_mean, image_change
from service.loop.loop import RenderLoop, exposed_change
from service.loop.spec import LoopSpec
from service.jobs.checkpoint_format import read_state, write_state

SIZE = 16
SCALE = 1.5


def test_image_change_is_the_mean_smape_between_the_two_images():
    a = np.full((2, 2, 3), 1.0, np.float32)
    b = a.copy()
    assert image_change(a, b) == 0.0
    b[0, 0] = 3.0  # |1 − 3| / (1 + 3 + 0.01) on one pixel of four
    assert image_change(a, b) == pytest.approx((2.0 / 4.01) / 4)


def test_image_change_counts_non_finite_values_as_zero_and_refuses_other_shapes():
    a = np.ones((2, 2, 3), np.float32)
    b = a.copy()
    b[0, 0, 0] = np.nan
    assert math.isfinite(image_change(a, b)) and image_change(a, b) == pytest.approx((1 / 1.01) / 12)
    with pytest.raises(ValueError, match="shape"):
        image_change(a, np.ones((3, 2, 3)))


def test_the_calibrated_map_keeps_its_ranking_and_has_the_geometric_mean_of_network_and_change():
    rng = np.random.default_rng(0)
    error = rng.uniform(0.001, 0.05, (8, 8)).astype(np.float32)
    calibrated = calibrate_by_change(error, 0.004, SCALE)
    expected_mean = math.sqrt(error.mean() * SCALE * 0.004)
    assert calibrated.mean() == pytest.approx(expected_mean, rel=1e-5)
    assert calibrated_mean(float(error.mean()), 0.004, SCALE) == pytest.approx(expected_mean)
    np.testing.assert_allclose(calibrated / error, calibrated.mean() / error.mean(), rtol=1e-5)  # one factor


def test_without_a_change_or_a_scale_or_any_error_the_map_is_left_alone():
    error = np.full((4, 4), 0.02, np.float32)
    assert calibrate_by_change(error, None, SCALE) is error
    assert calibrate_by_change(error, 0.01, None) is error
    assert calibrate_by_change(error, float("nan"), SCALE) is error
    zero = np.zeros((4, 4), np.float32)
    assert calibrate_by_change(zero, 0.01, SCALE) is zero


@pytest.fixture(scope="module")
def calibrated_networks(tiny_networks) -> Networks:
    """The tiny networks with an error network that carries a change scale (seeded, untrained)."""
    torch.manual_seed(1)
    error = ErrorPredictor(ErrorPredictorConfig(width=8, **{**PLAIN_ERROR_NETWORK, "change_scale": SCALE})).eval()
    return Networks(tiny_networks.denoiser, error)


def make_loop(networks: Networks, **overrides) -> RenderLoop:
    spec = LoopSpec(scene="cornell-box", width=SIZE, height=SIZE, **{"max_iterations": 3, **overrides})
    return RenderLoop(spec, networks)


def test_the_first_iteration_reports_the_network_and_later_ones_the_change_calibrated_mean(calibrated_networks):
    # the change is measured at the exposure of the samples then (models.exposure): keep each mean,
    # and between the denoiser's own images (the records carry the final ones, service.loop.final_image)
    loop = make_loop(calibrated_networks)
    runs = [(r, r.buffers[0].mean.copy(), loop.denoised_only()[0].copy()) for r in loop.run()]
    records = [r for r, _, _ in runs]
    first, *later = records
    assert first.predicted_error == pytest.approx(first.network_error)  # nothing to compare with yet
    for (_, _, before), (record, samples, denoised) in zip(runs, runs[1:]):
        change = exposed_change(before, denoised, samples)
        assert change > 0
        assert record.predicted_error == pytest.approx(calibrated_mean(record.network_error, change, SCALE), rel=1e-4)
        assert record.predicted_error != pytest.approx(record.network_error, rel=1e-3)
        assert record.error[0].mean() == pytest.approx(record.predicted_error, rel=1e-5)


def test_a_network_without_a_change_scale_reports_its_own_mean(tiny_networks):
    for record in make_loop(tiny_networks).run():
        assert record.predicted_error == pytest.approx(record.network_error)


def test_a_repeated_pass_within_an_iteration_keeps_the_change_it_measured(calibrated_networks):
    """Denoising again with the same samples (a restart's rebuild, a worker's missing frame)
    must not read a zero change from the image against itself."""
    loop = make_loop(calibrated_networks, max_iterations=2)
    *_, last = loop.run()
    loop.denoise_step({})
    np.testing.assert_allclose(loop.state.error_maps[0], last.error[0], rtol=1e-5, atol=1e-9)


def test_a_lambda_edit_between_iterations_still_compares_images_made_with_one_lambda(calibrated_networks):
    loop = make_loop(calibrated_networks, max_iterations=2)
    run = loop.run()
    next(run)
    lam = np.full((SIZE, SIZE), 4.0, np.float32)
    loop.set_lambda(lam)
    before = loop.denoised_only()[0].copy()  # the first iteration's denoised image, now at λ = 4
    second = next(run)
    change = exposed_change(before, loop.denoised_only()[0], second.buffers[0].mean)
    assert second.predicted_error == pytest.approx(calibrated_mean(second.network_error, change, SCALE), rel=1e-4)


def test_a_resumed_loop_reports_the_network_until_it_has_an_image_of_its_own(calibrated_networks, tmp_path):
    first = make_loop(calibrated_networks, max_iterations=3)
    run = first.run()
    next(run)
    write_state(first.state, tmp_path / "state")
    resumed = RenderLoop(first.spec, calibrated_networks, state=read_state(tmp_path / "state"))
    resumed_run = resumed.run()
    second = next(resumed_run)
    second_denoised = resumed.denoised_only()[0].copy()  # the denoiser's own images are what the change compares
    third = next(resumed_run)
    assert second.predicted_error == pytest.approx(second.network_error)
    change = exposed_change(second_denoised, resumed.denoised_only()[0], third.buffers[0].mean)
    assert third.predicted_error == pytest.approx(calibrated_mean(third.network_error, change, SCALE), rel=1e-4)


def test_the_calibration_changes_the_reported_error_never_where_samples_go(calibrated_networks):
    """Allocation is proportional to the map, so one factor on it moves no sample."""
    plain = ErrorPredictor(ErrorPredictorConfig(width=8, **PLAIN_ERROR_NETWORK)).eval()
    plain.load_state_dict(calibrated_networks.error_predictor.state_dict())
    def run(networks: Networks) -> list[tuple[np.ndarray, object]]:  # the buffers are the loop's own: copy each
        return [(r.buffers[0].spp.copy(), r) for r in make_loop(networks).run()]
    with_change = run(calibrated_networks)
    without = run(Networks(calibrated_networks.denoiser, plain))
    for (spp_a, a), (spp_b, b) in zip(with_change, without):
        np.testing.assert_array_equal(spp_a, spp_b)
        assert a.network_error == pytest.approx(b.network_error, rel=1e-6)
    with_change, without = with_change[-1][1], without[-1][1]
    assert with_change.predicted_error != pytest.approx(without.predicted_error, rel=1e-3)


def test_a_job_with_a_target_error_splits_its_first_iteration_and_calibrates_that_mean_too(calibrated_networks):
    """Iteration 0 renders spp_first/2 twice (the first half is pass 0, as a loop of spp_first/2
    renders it) and measures the change between the halves' denoised images."""
    half_loop = make_loop(calibrated_networks, spp_first=8, max_iterations=1)
    next(half_loop.run())
    half = half_loop.denoised_only()[0]  # the denoiser's own images are what the change compares
    loop = make_loop(calibrated_networks, spp_first=16, max_iterations=1, target_error=1e-9)
    first = next(loop.run())
    assert first.spp_mean == 16 and loop.state.buffers[0].passes == 2
    assert loop.session.full_calls == 2  # the half, then the whole
    change = exposed_change(half, loop.denoised_only()[0], first.buffers[0].mean)
    assert first.predicted_error == pytest.approx(calibrated_mean(first.network_error, change, SCALE), rel=1e-4)


def test_without_a_target_error_or_with_an_odd_first_count_the_first_iteration_is_one_pass(calibrated_networks):
    for overrides in ({}, {"spp_first": 15, "target_error": 1e-9}):
        loop = make_loop(calibrated_networks, max_iterations=1, **overrides)
        first = next(loop.run())
        assert loop.state.buffers[0].passes == 1 and loop.session.full_calls == 1
        assert first.predicted_error == pytest.approx(first.network_error)
