"""FrameBuffer statistics: which pixels count as converged."""
from __future__ import annotations

import dataclasses

import numpy as np

from service.render.framebuffer import CONVERGED_MIN_SPP, FrameBuffer


def buffer_with(samples: list[list[float]]) -> FrameBuffer:
    """A 1×N buffer whose pixel i received samples[i] (grey radiance)."""
    buffer = FrameBuffer.empty(1, len(samples))
    for i, values in enumerate(samples):
        values = np.asarray(values, dtype=np.float64)
        buffer.radiance_sum[0, i] = values.sum()
        buffer.radiance_sq_sum[0, i] = (values**2).sum()
        buffer.spp[0, i] = len(values)
    return buffer


def test_a_pixel_is_converged_only_when_enough_samples_all_agreed():
    n = CONVERGED_MIN_SPP
    buffer = buffer_with([[0.0] * n, [0.37] * n, [0.37] * (n - 1) + [0.38], [0.0] * (n - 1)])
    np.testing.assert_array_equal(buffer.converged()[0], [True, True, False, False])


def test_a_surface_whose_samples_were_all_zero_is_not_converged():
    # Rare indirect light can miss 16 times in a row; only a pixel that saw nothing is exact at 0.
    buffer = buffer_with([[0.0] * CONVERGED_MIN_SPP, [0.0] * CONVERGED_MIN_SPP])
    buffer.depth_sum[0, 1] = 3.0 * CONVERGED_MIN_SPP  # pixel 1's primary rays hit a surface
    np.testing.assert_array_equal(buffer.converged()[0], [True, False])


def test_a_missed_pixel_within_the_filters_reach_of_a_lit_one_is_not_converged():
    """Under a wide filter, 16 misses beside the ground do not make a pixel's value exact."""
    n = CONVERGED_MIN_SPP
    buffer = buffer_with([[0.0] * n] * 5 + [[0.5] * (n - 1) + [0.6]])   # five misses, then a noisy surface
    buffer.depth_sum[0, 5] = 2.0 * n
    reach = {footprint: dataclasses.replace(buffer, footprint=footprint).converged()[0] for footprint in (0, 1, 2)}
    np.testing.assert_array_equal(reach[0], [True] * 5 + [False])
    np.testing.assert_array_equal(reach[1], [True] * 4 + [False, False])
    np.testing.assert_array_equal(reach[2], [True] * 3 + [False] * 3)


def test_two_flat_emitters_side_by_side_are_not_converged_where_the_filter_mixes_them():
    n = CONVERGED_MIN_SPP
    buffer = buffer_with([[2.0] * n] * 3 + [[5.0] * n] * 3)
    np.testing.assert_array_equal(buffer.converged()[0], [True] * 6)
    buffer.footprint = 1
    np.testing.assert_array_equal(buffer.converged()[0], [True, True, False, False, True, True])


def test_a_background_pixel_beside_an_edge_is_converged_but_not_settled_under_the_box():
    """16 misses beside a lit pixel: exact for the image under the box (`converged`), but an edge
    with a few per cent coverage could hide in it, so the allocator does not leave it (`settled`)."""
    n = CONVERGED_MIN_SPP
    buffer = buffer_with([[0.0] * n] * 4 + [[0.5] * (n - 1) + [0.6]])   # four misses, then a noisy surface
    buffer.depth_sum[0, 4] = 2.0 * n
    np.testing.assert_array_equal(buffer.converged()[0], [True] * 4 + [False])
    np.testing.assert_array_equal(buffer.settled()[0], [True] * 3 + [False, False])
    buffer.footprint = 2   # a wider filter's reach decides both
    np.testing.assert_array_equal(buffer.settled()[0], buffer.converged()[0])
    np.testing.assert_array_equal(buffer.settled()[0], [True] * 2 + [False] * 3)


def test_the_film_edge_does_not_unsettle_a_uniform_background():
    buffer = FrameBuffer.empty(4, 5)
    buffer.spp[:] = CONVERGED_MIN_SPP                       # every ray missed: radiance and depth 0
    buffer.footprint = 2
    assert buffer.converged().all()


def test_a_copy_keeps_the_filters_reach():
    buffer = FrameBuffer.empty(2, 2)
    buffer.footprint = 2
    assert buffer.copy().footprint == 2


def splat_buffer(weights: list[list[float]], values: list[list[float]]) -> FrameBuffer:
    """A 1×N buffer whose pixel i got splats of grey `values[i]` with weights `weights[i]`."""
    buffer = buffer_with([[0.0]] * len(weights))
    buffer.add_splat(np.zeros((1, len(weights), 11)))
    for i, (w, v) in enumerate(zip(weights, values)):
        w, v = np.asarray(w, dtype=np.float64), np.asarray(v, dtype=np.float64)
        buffer.splat_weight[0, i] = w.sum()
        buffer.splat_radiance[0, i] = (w * v).sum()
        buffer.splat_sq_radiance[0, i] = (w * w * v).sum()
        buffer.splat_sq_radiance_sq[0, i] = (w * w * v * v).sum()
        buffer.splat_weight_sq[0, i] = (w * w).sum()
    return buffer


def test_the_raw_image_is_the_weight_normalised_splat_and_its_variance_that_of_the_mean_for_equal_weights():
    values = [0.2, 0.5, 0.9, 1.4]
    buffer = splat_buffer([[0.5] * 4], [values])
    assert np.allclose(buffer.raw[0, 0], np.mean(values))
    # equal weights: the unbiased variance of the mean, whatever the weights' scale
    assert np.allclose(buffer.raw_variance[0, 0], np.var(values, ddof=1) / 4, rtol=1e-5)


def test_negative_lobe_weights_add_to_the_raw_variance_instead_of_cancelling_it():
    values, weights = np.array([0.2, 0.5, 0.9, 1.4, 3.0]), np.array([1.0, 1.0, 1.0, 1.0, -0.3])
    lobed = splat_buffer([weights], [values])
    estimate = (weights * values).sum() / weights.sum()
    assert np.allclose(lobed.raw[0, 0], estimate, rtol=1e-6)
    # A signed second moment Σw·L²/Σw − R² goes negative here: the bright sample's negative weight
    # subtracts its spread. The ratio estimator's variance carries w² in every term.
    assert (weights * values**2).sum() / weights.sum() - estimate**2 < 0
    n_eff = weights.sum() ** 2 / (weights**2).sum()
    delta = (weights**2 * (values - estimate) ** 2).sum() / weights.sum() ** 2 * n_eff / (n_eff - 1)
    assert np.allclose(lobed.raw_variance[0, 0], delta, rtol=1e-5) and delta > 0


def test_a_box_filtered_buffer_reads_its_raw_image_from_its_own_samples():
    buffer = buffer_with([[0.2, 0.4], [1.0, 3.0]])
    assert buffer.splat_weight is None
    np.testing.assert_array_equal(buffer.raw, buffer.mean)
    np.testing.assert_array_equal(buffer.raw_variance, buffer.variance)


def test_copies_and_checkpoints_keep_the_splat_sums(tmp_path):
    from service.jobs.checkpoint_format import read_state, write_state
    from service.loop.state import LoopState

    buffer = splat_buffer([[0.5, 0.7], [1.0]], [[0.2, 0.4], [2.0]])
    copy = buffer.copy()
    buffer.splat_weight[0, 0] = 99.0
    assert copy.splat_weight[0, 0] == 1.2
    state = LoopState(iteration=1, buffers=[copy], lam_map=np.ones((1, 2), np.float32), error_maps=[None])
    restored = read_state(write_state(state, tmp_path / "checkpoint")).buffers[0]
    np.testing.assert_array_equal(restored.raw, copy.raw)
    np.testing.assert_array_equal(restored.raw_variance, copy.raw_variance)
