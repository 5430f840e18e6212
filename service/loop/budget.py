"""The default budget: a job that gives no stopping rule renders what the scene asks for.

Mitsuba renders a scene with its sensor's `<sampler><integer name="sample_count" …/>` samples
per pixel (after `-D`, our `--param`): so does the loop when the job names no stopping rule —
that count becomes the mean spp the job ends at (`spp_budget`), the first iteration renders
at most `spp_first` (16) and at most the budget, and each later one doubles the total until the
budget is spent. A scene that declares no sample_count, and every built-in scene, keeps the
loop's own default: DEFAULT_ITERATIONS (4) iterations, 16 → 128 spp. Any explicit stopping rule
(`--spp`, `--spp-budget`, `--iterations`, `--time-limit`, `--target-error`, or the API's fields)
wins over the scene.
"""
from __future__ import annotations

from dataclasses import replace
from typing import Iterable

from service.loop.spec import SERVICE_LIMITS, JobLimits, LoopSpec

STOPPING_RULES = ("max_iterations", "spp_budget", "time_limit", "target_error")
SCENE_BUDGET = "scene"  # LoopSpec.budget_source when spp_budget is the scene's sample_count
# LoopSpec.budget_source when max_iterations is the service's cap: the job gave a time limit
# (or target error) and nothing that bounds its samples (rules_as_given).
ITERATIONS_FROM_LIMITS = "limits"


def names_a_stopping_rule(given: Iterable[str]) -> bool:
    """Whether the request's explicitly given field names include a stopping rule."""
    return any(name in STOPPING_RULES for name in given)


def scene_budget(spec: LoopSpec, sample_count: int | None) -> LoopSpec:
    """`spec` (which gave no stopping rule) with the scene's sample count as its budget; `spec`
    itself when the scene declares none."""
    if sample_count is None or sample_count < 1:
        return spec
    return replace(spec, max_iterations=None, spp_budget=float(sample_count),
                   spp_first=min(spec.spp_first, sample_count), budget_source=SCENE_BUDGET)


def rules_as_given(spec: LoopSpec, given: set[str]) -> LoopSpec:
    """A service job that names stopping rules but not max_iterations stops by those rules, not
    also after the default DEFAULT_ITERATIONS (which is for a job that names none): a time limit
    alone iterates until its time is spent. Without an spp budget nothing else bounds the
    samples, so the iteration cap becomes the service's own (fit_iteration_cap)."""
    if "max_iterations" in given or not given & {"spp_budget", "time_limit", "target_error"}:
        return spec
    if "spp_budget" in given:
        return replace(spec, max_iterations=None)
    return replace(spec, max_iterations=None, budget_source=ITERATIONS_FROM_LIMITS)


def fit_iteration_cap(spec: LoopSpec, film_width: int, film_height: int, limits: JobLimits = SERVICE_LIMITS) -> LoopSpec:
    """A rules_as_given spec with the most iterations the service's limits allow for this film:
    at most max_iterations, and the doubling samples within max_total_samples."""
    if spec.budget_source != ITERATIONS_FROM_LIMITS or spec.max_iterations is not None:
        return spec
    pixels = (spec.width or film_width) * (spec.height or film_height) * spec.frames
    cap = 1
    while cap < limits.max_iterations and pixels * spec.spp_first * 2.0 ** cap <= limits.max_total_samples:
        cap += 1
    return replace(spec, max_iterations=cap)


def describe_budget(spec: LoopSpec) -> str:
    """`budget: …` as --explain and the CLI's summary line print it."""
    if spec.budget_source == SCENE_BUDGET and spec.spp_budget is not None:
        return f"budget: {spec.spp_budget:g} spp from the scene's sampler (sample_count)"
    rules = []
    if spec.max_iterations is not None:
        last = spec.spp_first * 2 ** (spec.max_iterations - 1)
        plural = "s" if spec.max_iterations > 1 else ""
        spp = f"{spec.spp_first} spp" if spec.max_iterations == 1 else f"{spec.spp_first} → {last} spp"
        rules.append(f"{spec.max_iterations} iteration{plural} ({spp})")
    if spec.spp_budget is not None:
        rules.append(f"{spec.spp_budget:g} spp")
    if spec.time_limit is not None:
        rules.append(f"{spec.time_limit:g} s")
    if spec.target_error is not None:
        rules.append(f"predicted SMAPE {spec.target_error:g}")
    return "budget: " + ", ".join(rules) + (", whichever comes first" if len(rules) > 1 else "")
