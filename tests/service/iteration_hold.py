"""Test-side hold for server processes (never imported by the product): a job can be made to stay
inside one iteration's render until it is stopped, instead of a test sizing a job "long enough"
to act within.

A job long enough to outlast a test's actions on a slow machine is too short on a fast one (the
job finishes before the kill, the SIGTERM or the queue fill it was meant to be running for) and
costs the shared cores minutes of rendering that compete with the test itself. Held, a job is
`running` for as long as the test needs, renders nothing, and still stops the product's own way:
the hold calls the loop's per-chunk progress callback, whose should_stop check (cancel, shutdown,
a lost lease) raises IterationInterrupted as it does between the chunks of a real render.

service_launcher.py installs it when RENDERLOOP_TEST_HOLD is set to `ITERATION` or
`ITERATION:SEED`: jobs (of that seed only, when given) hold once ITERATION iterations are done;
a server started without it renders every job as written.
"""
from __future__ import annotations

import threading
import time

ENV = "RENDERLOOP_TEST_HOLD"
POLL_SECONDS = 0.02


def hold_value(iteration: int, seed: int | None = None) -> str:
    """The environment value that holds jobs (of `seed`, when given) after `iteration` iterations."""
    return f"{iteration}" if seed is None else f"{iteration}:{seed}"


def install(value: str) -> None:
    """Patch service.loop.loop so that matching jobs hold in their render (see the module doc)."""
    from service.loop import loop as loop_module

    iteration, _, seed = value.partition(":")
    hold_from, hold_seed = int(iteration), (int(seed) if seed else None)
    holding = threading.local()
    render_step, render_samples = loop_module.RenderLoop.render_step, loop_module.render_samples

    def held_render_step(self, timings, should_stop=lambda: False):
        holding.now = self.state.iteration >= hold_from and hold_seed in (None, self.spec.seed)
        try:
            return render_step(self, timings, should_stop)
        finally:
            holding.now = False

    def held_render_samples(*args, progress, **kwargs):
        while getattr(holding, "now", False):
            progress(0)  # the loop's own check: raises IterationInterrupted once the job must stop
            time.sleep(POLL_SECONDS)
        return render_samples(*args, progress=progress, **kwargs)

    loop_module.RenderLoop.render_step = held_render_step
    loop_module.render_samples = held_render_samples
