"""Hard inputs to the loop's steps: corrupted accumulators, extreme λ maps, budgets below the
pixel count, an error map with all its mass in one pixel."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from hardcase_checks import assert_finite_frame, doubling_totals, run_checked
from service.loop.allocate import ALLOCATORS, DEFAULT_CAP_MULTIPLE, allocate_samples, allocation_weights
from models.pretrained import Networks
from service.loop.loop import RenderLoop
from service.loop.spec import LoopSpec

SIZE = 16
PIXELS = SIZE * SIZE


def make_loop(nets, error_predictor=None, **spec) -> RenderLoop:
    spec = {"max_iterations": 3, "allocator": "error", **spec}
    return RenderLoop(LoopSpec(scene="fireflies", width=SIZE, height=SIZE, **spec),
                      Networks(nets[0], error_predictor or nets[1]))


def test_nan_and_inf_injected_into_the_accumulators(nets):
    loop = make_loop(nets)
    run = loop.run()
    next(run)
    buffer = loop.state.buffers[0]
    buffer.radiance_sum[0, 0] = np.nan
    buffer.radiance_sum[0, 1, 1] = np.inf
    buffer.radiance_sq_sum[1, 1] = np.inf
    buffer.radiance_sq_sum[1, 2, 0] = np.nan
    buffer.albedo_sum[2, 2] = np.nan
    buffer.normal_sum[3, 3] = -np.inf
    buffer.depth_sum[4, 4] = np.nan
    # The rest of the loop — allocation from the corrupted frame, rendering, denoising, error
    # prediction — and every output layer must stay finite, with exact budgets.
    totals = doubling_totals(PIXELS, 16, 3)
    for i, record in enumerate(run, start=1):
        assert int(record.buffers[0].spp.sum()) == totals[i]
        assert np.isfinite(record.denoised[0]).all() and record.denoised[0].min() >= 0
        assert np.isfinite(record.error[0]).all() and record.error[0].min() >= 0
    for frame in loop.result_frames():
        assert_finite_frame(frame)


def lambda_maps() -> dict[str, np.ndarray]:
    y, x = np.mgrid[:SIZE, :SIZE]
    return {
        "all 1": np.ones((SIZE, SIZE), np.float32),
        "all 10": np.full((SIZE, SIZE), 10.0, np.float32),
        "halves": np.where(x < SIZE // 2, 1.0, 10.0).astype(np.float32),
        "pixel checkerboard": np.where((x + y) % 2 == 0, 1.0, 10.0).astype(np.float32),
        "one pixel at 10": np.pad(np.full((1, 1), 10.0, np.float32), ((5, SIZE - 6), (7, SIZE - 8)), constant_values=1),
    }


def test_lambda_maps_at_1_and_10_with_sharp_edges(nets):
    loop = make_loop(nets, max_iterations=2)
    run_checked(loop, doubling_totals(PIXELS, 16, 2))
    for name, lam in lambda_maps().items():
        images = loop.set_lambda(lam)
        assert len(images) == 1 and np.isfinite(images[0]).all() and images[0].min() >= 0, name
        for frame in loop.result_frames():
            assert_finite_frame(frame)
            np.testing.assert_array_equal(frame.lam, lam)


@pytest.mark.parametrize("allocator", ALLOCATORS)
def test_iteration_budget_smaller_than_the_pixel_count(nets, allocator):
    # 1 spp uniform first, then a budget of 1.25 spp mean: the second iteration has 64 samples
    # for 256 pixels, so most pixels get none.
    loop = make_loop(nets, allocator=allocator, spp_first=1, max_iterations=None, spp_budget=1.25)
    totals, records = [], []
    for record in loop.run():  # records share the live buffers: read the totals as they come
        totals.append(int(record.buffers[0].spp.sum()))
        records.append(record)
    assert totals == [PIXELS, PIXELS + PIXELS // 4]
    assert records[-1].stop_reason == "spp_budget"
    new = records[-1].buffers[0].spp - 1
    assert new.min() == 0 and new.max() >= 1
    for frame in loop.result_frames():
        assert_finite_frame(frame)


@pytest.mark.parametrize("budget", [0, 1, 7, PIXELS - 1])
@pytest.mark.parametrize("kind", ALLOCATORS)
def test_allocations_below_one_sample_per_pixel_are_exact(kind, budget):
    rng = np.random.default_rng(budget)
    weights = allocation_weights(kind, predicted_error=rng.random((SIZE, SIZE)),
                                 relative_variance=rng.random((SIZE, SIZE, 3)), shape=(SIZE, SIZE))
    counts = allocate_samples(weights, budget, seed=3)
    assert counts.sum() == budget and counts.min() >= 0 and counts.max() <= 1


class OnePixelError(torch.nn.Module):
    """An error "prediction" with all its mass in one pixel."""

    change_scale: float | None = None   # models.error_predictor.ErrorMap
    reads_disagreement = False

    def __init__(self, y: int, x: int, value: float) -> None:
        super().__init__()
        self.y, self.x, self.value = y, x, value

    def forward(self, frame, denoised: torch.Tensor) -> torch.Tensor:
        error = torch.zeros_like(denoised[:, :1])
        error[..., self.y, self.x] = self.value
        return error


@pytest.mark.parametrize("value", [1.0, 1e30])
def test_error_map_with_all_mass_in_one_pixel(nets, value):
    loop = make_loop(nets, error_predictor=OnePixelError(5, 9, value))
    records = run_checked(loop, doubling_totals(PIXELS, 16, 3))
    spp = records[-1].buffers[0].spp
    budget = doubling_totals(PIXELS, 16, 3)[-1] // 2
    cap = max(math.floor(DEFAULT_CAP_MULTIPLE * budget / PIXELS), math.ceil(budget / PIXELS))
    # Two error-driven iterations added at most `cap` each to the hot pixel; every pixel got
    # at least its first 16 and some of the floor share.
    assert spp[5, 9] > np.median(spp) and spp[5, 9] - 16 <= 2 * cap
    assert spp.min() >= 16


@pytest.mark.parametrize("hot", [1.0, 1e30, np.inf, np.nan])
def test_allocating_from_a_one_pixel_error_map_is_exact(hot):
    weights = np.zeros((7, 13))
    weights[3, 4] = hot
    for budget in (1, 90, 91 * 16, 10**6):
        counts = allocate_samples(allocation_weights("error", predicted_error=weights, shape=(7, 13)), budget)
        assert counts.sum() == budget and counts.min() >= 0
