"""The guarded development scenes' runs for tests/loop/test_shipped_networks.py: each scene's
first loop iteration with the shipped networks, OIDN on its render, and the same samples
denoised again with other networks (a network of the shipped architecture left untrained)."""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from bench.dev_references import DEFAULT_REFERENCE_DIR, dev_scenes, load_reference
from models.pretrained import Networks
from service.loop.loop import RenderLoop
from service.loop.oidn import oidn_image
from service.loop.spec import LoopSpec
from service.loop.state import LoopState


@dataclass(frozen=True)
class DevRun:
    """One guarded scene: its reference, the shipped networks' first iteration, OIDN on its render."""
    reference: np.ndarray
    record: object
    oidn: np.ndarray
    spec: LoopSpec     # the loop that made `record`


def guarded_scene(name: str):
    (scene,) = dev_scenes([name])
    reference, _ = load_reference(DEFAULT_REFERENCE_DIR, scene)
    return scene, reference


def first_iteration_spec(scene, seed: int = 0) -> LoopSpec:
    return LoopSpec(scene=str(scene.path), max_iterations=1, seed=seed)


def loop_on_samples(run: DevRun, networks: Networks) -> RenderLoop:
    """The loop resumed from `run`'s first-iteration buffers (a checkpoint) with other networks:
    its `denoised()` denoises, predicts the error and composes as the first iteration did."""
    buffers = [buffer.copy() for buffer in run.record.buffers]
    state = LoopState.new(len(buffers), *buffers[0].shape, run.spec.lam)
    state.buffers, state.iteration = buffers, 1
    return RenderLoop(run.spec, networks, state=state)


def final_image_of_samples(run: DevRun, networks: Networks) -> np.ndarray:
    """The loop's final image of `run`'s own first-iteration samples with other networks
    (loop_on_samples). Not a second seeded render: the same seed renders
    metals as another noise realisation in some processes (13 of 68 here: the same albedo and
    normals, radiance ~10 % apart per pixel), because Mitsuba's mesh merging at load
    (ParserConfig.merge_meshes, Mitsuba 3.9) orders its two area-light rectangles by address, and
    the emitter order decides which light a light sample picks. An image of other samples than
    OIDN's moved the pooled crop ratio by up to 0.003 (untrained seed 0 0.8346-0.8397 over runs)."""
    return loop_on_samples(run, networks).denoised()[0]


def render_dev_runs(shipped: Networks, names: Iterable[str], seed: int = 0) -> dict[str, DevRun]:
    """name → DevRun for each scene."""
    runs = {}
    for name in names:
        scene, reference = guarded_scene(name)
        spec = first_iteration_spec(scene, seed)
        record = next(iter(RenderLoop(spec, shipped).run()))
        buffer = record.buffers[0]
        runs[name] = DevRun(reference, record, oidn_image(buffer.mean, buffer.albedo, buffer.normal), spec)
    return runs
