"""How long a job has left: the doubling cost model.

Every iteration after the first renders as many samples as all earlier ones together (the
total doubles), so a linear extrapolation of the time per iteration under-estimates badly:
after two of four iterations the second half renders three times the samples of the first.
Here an iteration costs (mean spp it adds) × (measured seconds per spp) + (measured seconds of
the per-iteration passes: denoise, error prediction, allocation, I/O), both read from the
latest iteration that rendered (the first one also pays the kernels' compilation). The
stopping rules are replayed forward as the loop applies them (service/loop/loop.py
`_stop_after`); a target error cannot be known ahead, so the estimate is then an upper bound.
"""
from __future__ import annotations

from dataclasses import dataclass

from service.loop.spec import LoopSpec
from service.loop.stop_message import stop_message

RENDER_STAGE = "render"
MAX_SIMULATED = 64  # more iterations than any spec allows: beyond this no finite rule stops the job


@dataclass(frozen=True)
class IterationCost:
    """What one finished iteration took."""

    spp_added: float  # mean samples per pixel it added
    render_seconds: float
    other_seconds: float  # denoise, error, allocate, I/O: paid once per iteration, whatever its samples


@dataclass(frozen=True)
class Eta:
    """Seconds left (None: cannot be known) and, in words, what they rest on."""

    seconds: float | None
    basis: str


@dataclass(frozen=True)
class Progress:
    """Where a job stands after an iteration: its ETA and, on the last one, why it stopped."""

    eta: Eta
    stop_message: str | None = None


class CostModel:
    """Per-iteration costs measured so far; predicts the cost of an iteration adding `spp`."""

    def __init__(self) -> None:
        self.history: list[IterationCost] = []

    def observe(self, spp_added: float, timings: dict[str, float]) -> None:
        render = float(timings.get(RENDER_STAGE, 0.0))
        other = sum(float(s) for stage, s in timings.items() if stage != RENDER_STAGE)
        self.history.append(IterationCost(float(spp_added), render, other))

    @property
    def measured(self) -> bool:
        return any(cost.spp_added > 0 for cost in self.history)

    def seconds_per_spp(self) -> float:
        """The latest rendering iteration's rate: the largest sample count, least warm-up in it."""
        latest = next(cost for cost in reversed(self.history) if cost.spp_added > 0)
        return latest.render_seconds / latest.spp_added

    def fixed_seconds(self) -> float:
        return self.history[-1].other_seconds

    def iteration_seconds(self, spp_added: float) -> float:
        return spp_added * self.seconds_per_spp() + self.fixed_seconds()


@dataclass
class _Cursor:
    """The loop's state as the replay advances it."""

    iteration: int
    spp: float
    elapsed: float


def _stop_rule(spec: LoopSpec, at: _Cursor) -> str | None:
    """The rules of RenderLoop._stop_after that can be known ahead (all but the target error)."""
    if spec.max_iterations is not None and at.iteration >= spec.max_iterations:
        return "max_iterations"
    if spec.spp_budget is not None and at.spp >= spec.spp_budget - 1e-9:
        return "spp_budget"
    if spec.time_limit is not None and at.iteration > 0 and 2 * at.elapsed > spec.time_limit:
        return "time_limit"
    return None


def _spp_added(spec: LoopSpec, at: _Cursor) -> float:
    added = float(spec.spp_first) if at.iteration == 0 else at.spp  # the total doubles
    if spec.spp_budget is not None:
        added = max(0.0, min(added, spec.spp_budget - at.spp))
    return added


def estimate(spec: LoopSpec, model: CostModel, iteration: int, spp_mean: float, elapsed: float) -> Eta:
    """Seconds left for a job that has finished `iteration` iterations, reached `spp_mean` and
    spent `elapsed` seconds of loop time (what its time limit counts)."""
    if not model.measured:
        return Eta(None, "known after the first iteration is measured")
    at = _Cursor(iteration, spp_mean, elapsed)
    start = at.iteration
    seconds = 0.0
    rule = _stop_rule(spec, at)
    while rule is None and at.iteration - start < MAX_SIMULATED:
        cost = model.iteration_seconds(_spp_added(spec, at))
        at.spp += _spp_added(spec, at)
        at.iteration += 1
        at.elapsed += cost
        seconds += cost
        rule = _stop_rule(spec, at)
    if rule is None:
        return Eta(None, "unknown: only the target error stops this job, and when it is reached cannot be "
                         "known ahead")
    return Eta(seconds, _basis(spec, model, rule, at.iteration - start))


def _basis(spec: LoopSpec, model: CostModel, rule: str, left: int) -> str:
    if left == 0:
        return f"done: {rule} reached"
    if rule == "max_iterations":
        what = f"max_iterations ({spec.max_iterations})"
    elif rule == "spp_budget":
        what = f"the budget of {spec.spp_budget:g} spp"
    else:
        what = f"the {spec.time_limit:g} s time limit"
    plural = "s" if left > 1 else ""
    words = (f"{left} more iteration{plural} until {what}, each doubling the samples: "
             f"{model.seconds_per_spp():.3g} s per spp and {model.fixed_seconds():.3g} s per iteration "
             f"(denoise, error, I/O) as measured")
    if spec.target_error is not None:
        words += f"; an upper bound: the target error ({spec.target_error:g}) may stop it sooner"
    return words


class EtaTracker:
    """A worker's view of one running job: fed each finished iteration, answers its ETA."""

    def __init__(self, spec: LoopSpec, spp_mean: float = 0.0) -> None:
        self.spec = spec
        self.model = CostModel()
        self._spp = spp_mean  # a resumed job's samples so far

    def observe(self, spp_mean: float, timings: dict[str, float]) -> None:
        self.model.observe(max(0.0, spp_mean - self._spp), timings)
        self._spp = spp_mean

    def eta(self, iteration: int, elapsed: float) -> Eta:
        return estimate(self.spec, self.model, iteration, self._spp, elapsed)

    def after(self, iterations: int, spp_mean: float, timings: dict[str, float], elapsed: float,
              stop_reason: str | None, predicted_error: float | None = None) -> Progress:
        """One more finished iteration (`iterations` in all, `elapsed` s of loop time): the ETA,
        and on the last one why the job stopped, in words."""
        self.observe(spp_mean, timings)
        if stop_reason is not None:
            message = stop_message(self.spec, stop_reason, iterations, spp_mean, elapsed, predicted_error)
            return Progress(Eta(0.0, "finished"), message)
        return Progress(self.eta(iterations, elapsed))
