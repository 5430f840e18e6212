"""(x), the allocation by the *expected* true error: what the best predictor of a scene's error
could reach, as opposed to (o), which knows this very render's error.

(o) allocates (and composes the final image) by the true error map of the render it is refining,
its noise included: no network that predicts a scene's error can know where this render's
noise happened to land. The repeatable part of the error — what a perfect predictor of the
expected error knows — is estimated here by replicas: loops of the same scene with different
seeds (bench.loop_run.EXPECTED_BOUND_REPLICAS of them) run in lockstep, every one allocating by
the mean of the *other* replicas' true error maps of the same iteration (leave-one-out, so no
replica sees its own noise). Replica 0 has the loop seed of (b) and (d), so it shares their first
iteration's samples; it is the run reported. The gap (d) − (x) is what a better error network
could still buy; (x) − (o) is the render's own noise, which the ceiling of the per-pixel Spearman
(bench.calibration_ceiling) measures for the ranking alone.
"""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
import torch

from bench.common import BenchNetworks, OidnDenoise, image_metrics, true_error_map
from bench.loop_run import STAGES, BenchScene, BenchSettings, LoopMethod, MethodRun, Row, loop_spec, run_method
from models.frames import FrameTensors
from models.pretrained import Networks
from service.loop.loop import RenderLoop, converged_error
from service.loop.spec import IterationRecord
from service.loop.tensors import to_image

# Replica j's loop seed: the run's seed + j · this (a prime far above the seeds a run is given).
REPLICA_SEED_STRIDE = 104_729


class OwnTrueError(torch.nn.Module):
    """Stand-in error network of one replica: the true error map of its own denoised image,
    kept for the lockstep driver, which then hands the replica the others' mean instead."""

    change_scale: float | None = None   # models.error_predictor.ErrorMap: no calibration,
    reads_disagreement = False          # no disagreement input

    def __init__(self, reference: np.ndarray):
        super().__init__()
        self.reference = reference
        self.last: np.ndarray | None = None

    def forward(self, frame: FrameTensors, denoised: torch.Tensor) -> torch.Tensor:
        self.last = true_error_map(to_image(denoised), self.reference)
        return torch.from_numpy(self.last)[None, None]


def leave_one_out_means(maps: list[np.ndarray]) -> list[np.ndarray]:
    """For each map, the mean of all the others (float32, as error maps are)."""
    total = np.sum(maps, axis=0, dtype=np.float64)
    count = len(maps) - 1
    return [((total - m) / count).astype(np.float32) for m in maps]


def lockstep_iteration(loops: list[RenderLoop], stand_ins: list[OwnTrueError]) -> list[IterationRecord]:
    """One iteration of every replica: each renders (allocating by the map it was handed last) and
    denoises, then gets the leave-one-out mean of this iteration's true maps as its error map —
    the one its final image is composed with and its next allocation reads."""
    timings: list[dict] = [{} for _ in loops]
    seconds = []
    for loop, timing in zip(loops, timings):
        started = time.perf_counter()
        loop.render_step(timing)
        loop.denoise_step(timing)
        seconds.append(time.perf_counter() - started)
    for loop, mean_map in zip(loops, leave_one_out_means([s.last for s in stand_ins])):
        image, _, converged = loop.owned_outputs()[0]
        loop.adopt_denoised({0: (image, converged_error(converged, mean_map), converged)})
    return [loop.finish_step(timing, spent) for loop, timing, spent in zip(loops, timings, seconds)]


def run_expected_bound(scene: BenchScene, method: LoopMethod, settings: BenchSettings, nets: BenchNetworks,
                       reference: np.ndarray, replicas: int) -> MethodRun:
    """(x) on one scene: `replicas` loops in lockstep, each allocating by the leave-one-out mean of
    the replicas' true error maps; replica 0's rows (its stage times include the true maps, not
    the error network's cost: a bound's time means little)."""
    if replicas < 2:
        raise ValueError("the expected-error bound needs at least two replicas")
    stand_ins = [OwnTrueError(reference) for _ in range(replicas)]
    loops = [RenderLoop(loop_spec(scene, method, replace(settings, seed=settings.seed + REPLICA_SEED_STRIDE * j),
                                  settings.iterations),
                        Networks(nets.networks.denoiser, stand_in))
             for j, stand_in in enumerate(stand_ins)]
    rows, cumulative, final = [], 0.0, None
    for _ in range(settings.iterations):
        record = lockstep_iteration(loops, stand_ins)[0]
        stage = {name: float(record.timings.get(name, 0.0)) for name in STAGES}
        cumulative += sum(stage.values())
        image = record.denoised[0]
        rows.append(Row(scene.label, method.key, record.iteration, record.spp_mean, stage, cumulative,
                        image_metrics(image, reference), None))
        final = (image, record.buffers[0].spp.copy())
        if record.stop_reason is not None:
            break
    image, spp_map = final
    return MethodRun(method, rows, image, spp_map, None)


def run_bench_method(scene: BenchScene, method: LoopMethod, settings: BenchSettings, nets: BenchNetworks,
                     reference: np.ndarray, oidn: OidnDenoise | None = None) -> MethodRun:
    """Any of bench.loop_run.METHODS on one scene: the replicated bound here, the others one loop each."""
    if method.replicas:
        return run_expected_bound(scene, method, settings, nets, reference, method.replicas)
    return run_method(scene, method, settings, nets, reference, oidn)
