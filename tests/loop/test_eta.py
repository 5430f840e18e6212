"""The ETA's doubling cost model (service/loop/eta.py) and the stop reason in words
(service/loop/stop_message.py): the model replays the job's stopping rules over measured
per-iteration costs; on a real render it predicts the rest of a job within 2×, where a linear
extrapolation of the time per iteration (the old progress bar) under-estimates by more."""
from __future__ import annotations

import dataclasses
import time

import pytest

from service.loop.eta import CostModel, EtaTracker, estimate
from service.loop.loop import RenderLoop
from service.loop.budget import ITERATIONS_FROM_LIMITS, fit_iteration_cap, rules_as_given
from service.loop.spec import JobLimits, LoopSpec
from service.loop.stop_message import stop_message


def measured(*iterations: tuple[float, float, float]) -> CostModel:
    """A model fed (spp added, render seconds, other seconds) per iteration."""
    model = CostModel()
    for spp, render, other in iterations:
        model.observe(spp, {"render": render, "denoise": other})
    return model


def test_each_remaining_iteration_costs_its_doubled_samples_plus_the_fixed_passes():
    model = measured((16, 5.0, 0.5), (16, 1.6, 0.2))  # the first one paid the kernels' compilation
    eta = estimate(LoopSpec("cornell-box", max_iterations=4), model, iteration=2, spp_mean=32, elapsed=7.3)
    # iterations 3 and 4 add 32 and 64 spp at 0.1 s per spp, plus 0.2 s each
    assert eta.seconds == pytest.approx(32 * 0.1 + 0.2 + 64 * 0.1 + 0.2)
    assert "2 more iterations until max_iterations (4)" in eta.basis


def test_a_time_limit_is_replayed_as_the_loop_applies_it_and_a_target_error_makes_it_an_upper_bound():
    model = measured((16, 1.6, 0.0), (16, 1.6, 0.0))
    spec = LoopSpec("cornell-box", max_iterations=None, time_limit=30, target_error=0.01)
    eta = estimate(spec, model, iteration=2, spp_mean=32, elapsed=3.2)
    # 3.2 + 3.2 = 6.4 → 6.4 + 6.4 = 12.8 → 12.8 + 12.8 = 25.6: twice that is over 30, the loop stops there
    assert eta.seconds == pytest.approx(3.2 + 6.4 + 12.8)
    assert "the 30 s time limit" in eta.basis and "upper bound" in eta.basis
    alone = estimate(LoopSpec("cornell-box", max_iterations=None, target_error=0.01), model, 2, 32, 3.2)
    assert alone.seconds is None and "target error" in alone.basis


def test_an_spp_budget_caps_the_last_iteration_and_an_unmeasured_job_has_no_eta():
    model = measured((16, 1.6, 0.0))
    spec = LoopSpec("cornell-box", max_iterations=None, spp_budget=40)
    assert estimate(spec, model, 1, 16, 1.6).seconds == pytest.approx(16 * 0.1 + 8 * 0.1)
    assert estimate(spec, CostModel(), 0, 0, 0).seconds is None


def test_a_time_limit_alone_iterates_up_to_the_services_cap_instead_of_the_default_four_iterations():
    spec = rules_as_given(LoopSpec("cornell-box", time_limit=30), {"time_limit"})
    assert spec.max_iterations is None and spec.budget_source == ITERATIONS_FROM_LIMITS
    limits = JobLimits()
    assert fit_iteration_cap(spec, 32, 32, limits).max_iterations == limits.max_iterations
    # a large film: as many doublings as the total-sample cap allows
    big = fit_iteration_cap(spec, 2048, 2048, limits)
    assert 2048 * 2048 * 16 * 2.0 ** (big.max_iterations - 1) <= limits.max_total_samples
    assert 2048 * 2048 * 16 * 2.0 ** big.max_iterations > limits.max_total_samples
    # a rule that bounds the samples, given with it, is kept as asked
    given = LoopSpec("cornell-box", time_limit=30, max_iterations=6)
    assert rules_as_given(given, {"time_limit", "max_iterations"}) is given
    # a budget alone bounds the samples itself: no iteration cap beside it
    budget = rules_as_given(LoopSpec("cornell-box", spp_budget=256), {"spp_budget"})
    assert (budget.max_iterations, budget.budget_source) == (None, None)
    # no rule at all: the default iterations stay
    assert rules_as_given(LoopSpec("cornell-box"), {"width"}).max_iterations == 4


def test_the_stop_message_says_which_rule_ended_the_job_and_what_time_was_left_unused():
    capped = LoopSpec("cornell-box", max_iterations=4, time_limit=30)
    assert stop_message(capped, "max_iterations", 4, 128, 4.2) == (
        "stopped after 4 iterations (max_iterations 4) — 26 s of the 30 s time limit unused")
    by_limits = LoopSpec("cornell-box", max_iterations=12, time_limit=30, budget_source=ITERATIONS_FROM_LIMITS)
    assert "this server's cap" in stop_message(by_limits, "max_iterations", 12, 2048, 10)
    assert "the default" in stop_message(LoopSpec("cornell-box"), "max_iterations", 4, 128, 3)
    timed = stop_message(LoopSpec("cornell-box", max_iterations=None, time_limit=30), "time_limit", 5, 256, 16.2)
    assert timed.startswith("stopped after 5 iterations in 16.2 s of the 30 s time limit")
    assert stop_message(capped, None, 2, 32, 1.0) is None
    assert stop_message(capped, "canceled", 2, 32, 1.0) == "canceled after 2 iterations (32.0 spp)"


@pytest.mark.slow
def test_after_two_of_four_iterations_of_a_real_render_the_eta_is_within_2x_where_linear_extrapolation_is_not():
    """A render-bound job (no denoiser, uniform allocation, 96², 32 spp first): its second half
    renders three times the samples of its first."""
    spec = LoopSpec("cornell-box", width=96, height=96, spp_first=32, max_iterations=4, denoise=False,
                    allocator="uniform")
    # compile the kernels first, as a server that has rendered this scene before has them
    list(RenderLoop(dataclasses.replace(spec, max_iterations=2), None).run())
    loop, tracker = RenderLoop(spec, None), EtaTracker(spec)
    started, ends, predicted = time.perf_counter(), [], []
    for record in loop.run():
        ends.append(time.perf_counter() - started)
        progress = tracker.after(loop.state.iteration, record.spp_mean, record.timings, loop.state.elapsed,
                                 record.stop_reason)
        predicted.append(progress.eta.seconds)
    actual = ends[3] - ends[1]
    linear = ends[1] / 2 * 2  # the mean time per iteration so far × the iterations left
    assert 0.5 <= predicted[1] / actual <= 2.0, (predicted[1], actual, ends)
    assert actual / linear > 2.0, f"linear extrapolation would pass too: {linear:.2f} s for {actual:.2f} s ({ends})"
    assert predicted[3] == 0.0
