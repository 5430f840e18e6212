"""The loop's stopping rules in real settings, and no samples wasted where every sample agreed:
the shipped networks, the hand-written development scenes (scenes/dev, never trained on)."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from models.pretrained import load_networks
from service.loop.allocate import EDGE_SETTLE_SPP
from service.loop.loop import RenderLoop
from service.loop.spec import LoopSpec

DEV_SCENES = sorted((Path(__file__).resolve().parents[2] / "scenes" / "dev").glob("*/scene.xml"))
SIZE = 32


@pytest.fixture(scope="module")
def shipped():
    return load_networks()


def dev_loop(networks, scene: Path, **overrides) -> RenderLoop:
    spec = LoopSpec(scene=str(scene), width=SIZE, height=SIZE, **{"max_iterations": 3, **overrides})
    return RenderLoop(spec, networks)


@pytest.mark.parametrize("scene", DEV_SCENES, ids=lambda p: p.parent.name)
def test_pixels_whose_samples_all_agree_get_no_more_than_their_share(shipped, scene):
    """After iteration 0, the samples that land on pixels whose 16 samples all agreed, as did their
    neighbours' (empty background, a flat emitter), are at most what a uniform allocation would
    give them; those beside pixels that did not agree get no more than EDGE_SETTLE_SPP in all
    beyond that share."""
    loop = dev_loop(shipped, scene, max_iterations=2)
    first = next(loop.run())
    settled, converged = first.buffers[0].settled(), first.buffers[0].converged()
    before = first.buffers[0].spp.copy()
    *_, last = loop.run()
    added = last.buffers[0].spp - before
    share = settled.mean()  # what uniform sampling would send them
    spent = added[settled].sum() / added.sum()
    assert spent <= share + 1e-9, f"{settled.sum()} agreeing pixels took {spent:.1%} of the samples (share {share:.1%})"
    edge = converged & ~settled
    uniform_share = int(np.ceil(added.sum() / added.size))
    assert (last.buffers[0].spp[edge] <= np.maximum(EDGE_SETTLE_SPP, before[edge]) + uniform_share).all()


def test_target_error_stops_at_the_first_iteration_that_reaches_it(shipped):
    """A target below the first two iterations' predicted errors and above the third's stops
    exactly after the third. (The mean need not fall at every iteration: from the second on it is
    calibrated by the image's change, which can correct the first iteration's guess upwards.)"""
    scene = next(p for p in DEV_SCENES if p.parent.name == "hard_shadows")
    # a target no iteration reaches: the loop runs as a target-error job does (first iteration split)
    errors = [r.predicted_error for r in dev_loop(shipped, scene, max_iterations=4, target_error=1e-9).run()]
    assert errors[2] < min(errors[:2]), errors
    target = (errors[2] + min(errors[:2])) / 2
    records = list(dev_loop(shipped, scene, max_iterations=None, spp_budget=128, target_error=target).run())
    assert [r.stop_reason for r in records] == [None, None, "target_error"]
    assert records[-1].predicted_error <= target < records[-2].predicted_error


def test_time_limit_runs_several_iterations_and_never_overruns(shipped):
    scene = next(p for p in DEV_SCENES if p.parent.name == "hard_shadows")
    started = time.perf_counter()
    first = next(dev_loop(shipped, scene, max_iterations=1).run())
    one_iteration = time.perf_counter() - started
    limit = 12 * max(one_iteration, first.timings.get("render", 0.0))
    loop = dev_loop(shipped, scene, max_iterations=None, time_limit=limit)
    records = list(loop.run())
    assert records[-1].stop_reason == "time_limit"
    assert len(records) >= 2  # not a rule that always stops at once
    assert loop.state.elapsed <= limit
