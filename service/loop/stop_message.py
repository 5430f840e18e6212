"""Why a job stopped, in words: `stop_reason` stays the machine code (spec.STOP_REASONS), the
message says which rule ended the job and what the others left unused, so a job that ends
before its time limit says why ("stopped after 4 iterations (max_iterations 4) — 26 s of the
30 s time limit unused")."""
from __future__ import annotations

from service.loop.budget import ITERATIONS_FROM_LIMITS, SCENE_BUDGET
from service.loop.spec import DEFAULT_ITERATIONS, LoopSpec

UNUSED_SECONDS_WORTH_SAYING = 0.5


def _iterations(n: int) -> str:
    return f"{n} iteration{'s' if n != 1 else ''}"


def _unused_time(spec: LoopSpec, elapsed: float) -> str:
    if spec.time_limit is None or spec.time_limit - elapsed < UNUSED_SECONDS_WORTH_SAYING:
        return ""
    return f" — {spec.time_limit - elapsed:.0f} s of the {spec.time_limit:g} s time limit unused"


def _cap_words(spec: LoopSpec) -> str:
    if spec.budget_source == ITERATIONS_FROM_LIMITS:
        return "this server's cap: a time limit alone iterates until its time is spent, up to that cap"
    only_rule = spec.spp_budget is None and spec.time_limit is None and spec.target_error is None
    if only_rule and spec.max_iterations == DEFAULT_ITERATIONS:
        return f"max_iterations {spec.max_iterations}, the default when a job gives no stopping rule"
    return f"max_iterations {spec.max_iterations}"


def canceled_message(iterations: int = 0, spp_mean: float = 0.0) -> str:
    if not iterations:
        return "canceled before its first iteration finished"
    return f"canceled after {_iterations(iterations)} ({spp_mean:.1f} spp)"


def stop_message(spec: LoopSpec, reason: str | None, iterations: int, spp_mean: float, elapsed: float,
                 predicted_error: float | None = None) -> str | None:
    """The stop reason in words for a job that ran `iterations` iterations to `spp_mean` in
    `elapsed` seconds of loop time; None when it has not stopped."""
    done = _iterations(iterations)
    if reason is None:
        return None
    if reason == "canceled":
        return canceled_message(iterations, spp_mean)
    if reason == "max_iterations":
        return f"stopped after {done} ({_cap_words(spec)}){_unused_time(spec, elapsed)}"
    if reason == "spp_budget":
        source = " from the scene's sampler (sample_count)" if spec.budget_source == SCENE_BUDGET else ""
        return f"reached the budget of {spec.spp_budget:g} spp{source} after {done}{_unused_time(spec, elapsed)}"
    if reason == "time_limit":
        return (f"stopped after {done} in {elapsed:.1f} s of the {spec.time_limit:g} s time limit: the next "
                "iteration doubles the samples, so it would take about as long as all before it and overrun")
    if reason == "target_error":
        reached = f": predicted SMAPE {predicted_error:.4g} ≤ {spec.target_error:g}" if predicted_error is not None else ""
        return f"reached the target error after {done}{reached}{_unused_time(spec, elapsed)}"
    return f"stopped after {done} ({reason})"
