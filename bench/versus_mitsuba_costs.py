"""Each loop iteration's fixed costs at the benchmark's size, per megapixel: the network passes,
the copies between the sample buffers and the networks' tensors (host/device transfers on a GPU;
on the CPU, layout copies), the allocation, and what the job worker writes after every iteration
(checkpoint, previews).

Measured on a finished loop's final state, by calling the very functions the loop and the worker
call (`DenoiseSession.denoise / predict_error / relambda`, `frame_tensors`, `RenderLoop.denoised`, `LoopState.snapshot`,
`checkpoint_format.write_state`, `JobFiles.save_preview(preview_layers(…))`), each `repeats`
times, the median kept. The thread backend's worker (service/jobs/worker.py) copies the state
on the loop's thread (the snapshot: time the render waits) and writes the checkpoint and the
previews from that copy on a background thread (service/jobs/checkpoint_writer.py) while the
next iteration renders.
"""
from __future__ import annotations

import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch

from bench.versus_mitsuba_run import LoopRun
from service.jobs.artifacts import JobFiles, Preview
from service.jobs.checkpoint_format import write_state
from service.jobs.previews import preview_layers
from service.loop.allocate import iteration_budget
from service.loop.loop import RenderLoop, next_counts
from service.loop.oidn import oidn_tensor
from service.loop.tensors import frame_tensors, to_image
from service.render.framebuffer import FrameBuffer

# The stages of the table, in the order an iteration (and then the worker) runs them.
# (key, label, whether it is a fixed cost: independent of the samples rendered)
STAGES = (
    ("render", "render (the iteration's samples; not fixed: grows with spp)", False),
    ("allocate", "allocate (error map → per-pixel counts)", True),
    ("to_tensors", "buffers → network tensors (host → device on a GPU)", True),
    ("oidn_candidate", "OIDN candidate inside the denoiser (when the weights use one)", True),
    ("denoiser", "denoiser full pass (prepare + apply at λ, without its OIDN call)", True),
    ("error_network", "error network", True),
    ("to_host", "denoised image → host array (device → host on a GPU)", True),
    ("final_image", "final image (raw image + its variance, its share by window means, blend; once an "
                    "iteration, in its denoise stage)", True),
    ("lambda_tail", "λ tail from cached features (a λ edit)", True),
    ("snapshot", "state snapshot on the loop's thread (LoopState.snapshot, into the last one's arrays)", True),
    ("checkpoint", "checkpoint write (checkpoint_format.write_state, atomic; background thread)", True),
    ("preview", "preview write (all layers, atomic; background thread)", True),
)
RENDER_PATH_WRITES = ("snapshot",)  # what the loop's thread pays for the worker's writes
BACKGROUND_WRITES = ("checkpoint", "preview")


@dataclass
class FixedCosts:
    scene: str
    megapixels: float
    ms: dict[str, float]  # median milliseconds per stage call ("render": the last iteration's)
    iteration_ms: list[float]  # wall time of each of the loop's iterations (its four stages)
    render_ms: list[float]  # the render stage of each
    takes_candidate: bool  # whether the denoiser's weights take OIDN's image as an input (its config)

    def per_megapixel(self, stage: str) -> float:
        return self.ms[stage] / self.megapixels

    @property
    def worker_ms(self) -> float:
        """What the worker's writes add to each iteration on the loop's thread."""
        return sum(self.ms[s] for s in RENDER_PATH_WRITES)

    @property
    def background_ms(self) -> float:
        """The checkpoint and preview writes the background thread does meanwhile."""
        return sum(self.ms[s] for s in BACKGROUND_WRITES)

    def share(self, stage: str, iteration: int) -> float:
        """`stage`'s time as a share of iteration `iteration` with the worker's writes added (the
        render: that iteration's own)."""
        ms = self.render_ms[iteration] if stage == "render" else self.ms[stage]
        return ms / (self.iteration_ms[iteration] + self.worker_ms)

    @property
    def stall_share(self) -> float:
        """The worker's writes as a share of the whole job's wall time (the render waits that long)."""
        writes = self.worker_ms * len(self.iteration_ms)
        return writes / (sum(self.iteration_ms) + writes)


def _synchronize() -> None:
    """Wait for the GPU's queued work: a CUDA call returns before its kernels finish."""
    if torch.cuda.is_initialized():
        torch.cuda.synchronize()


def _median_ms(call: Callable[[], object], repeats: int) -> float:
    times = []
    for _ in range(repeats):
        _synchronize()
        started = time.perf_counter()
        call()
        _synchronize()
        times.append(time.perf_counter() - started)
    return 1000 * statistics.median(times)


def _compose_final_anew(loop: RenderLoop) -> list:
    """The final images as the loop composes them once per iteration (service/loop/final_image.py):
    the kept raw image and share forgotten, as new samples or a new error map forget them."""
    loop._forget_final()
    for buffer in loop.state.buffers:
        buffer.invalidate()
    return loop.denoised()


def _anew(buffer: FrameBuffer, call: Callable[[], object]) -> Callable[[], object]:
    """`call` as its first read after a pass of samples: what the buffer derives from its sums
    (FrameBuffer.cached: the mean, the converged mask, …) forgotten first, as a render forgets it."""
    def first_read() -> object:
        buffer.invalidate()
        return call()
    return first_read


def measure_fixed_costs(label: str, run: LoopRun, repeats: int = 3) -> FixedCosts:
    loop, record = run.loop, run.last
    session = loop.session
    buffer = loop.state.buffers[0]
    lam = loop.state.lam_map
    denoiser = session.networks.denoiser
    frame = frame_tensors(buffer, session.device)  # OIDN's input where the loop gives it: the networks' device
    images = session.denoise(loop.state.buffers, lam)
    ms = {
        "render": 1000 * run.curve.points[-1].stages["render"],
        # the next iteration's allocation from this state (iteration 0's is a constant fill)
        # with the converged mask it reads (the loop computes it once per iteration, in denoise_step)
        "allocate": _median_ms(_anew(buffer, lambda: next_counts(loop.spec.allocator, buffer, loop.state.error_maps[0],
                                                                 iteration_budget(int(buffer.spp.sum())), seed=0)),
                               repeats),
        "to_tensors": _median_ms(_anew(buffer, lambda: frame_tensors(buffer, session.device)), repeats),
        "oidn_candidate": _median_ms(lambda: oidn_tensor(frame), repeats)
        if denoiser.config.oidn_candidate else 0.0,
        "denoiser": _median_ms(lambda: session.denoise(loop.state.buffers, lam), repeats),
        "error_network": _median_ms(lambda: session.predict_error(images), repeats),
        "to_host": _median_ms(lambda: to_image(images[0]), repeats),
        "final_image": _median_ms(lambda: _compose_final_anew(loop), repeats),
        "lambda_tail": _median_ms(lambda: session.relambda(lam), repeats),
    }
    ms["denoiser"] = max(0.0, ms["denoiser"] - ms["oidn_candidate"] - ms["to_tensors"])
    with tempfile.TemporaryDirectory(prefix="versus-mitsuba-io-") as folder:
        files = JobFiles(Path(folder))
        layers = preview_layers(loop, record)
        spare = loop.state.snapshot()  # the worker overwrites the last write's copy (checkpoint_writer.py)
        ms["snapshot"] = _median_ms(lambda: loop.state.snapshot(spare), repeats)
        ms["checkpoint"] = _median_ms(lambda: write_state(loop.state, files.state_dir), repeats)
        ms["preview"] = _median_ms(lambda: [files.save_preview(f, Preview(1, frame_layers))
                                            for f, frame_layers in enumerate(layers)], repeats)
    iteration_ms = [1000 * sum(p.stages.values()) for p in run.curve.points]
    render_ms = [1000 * p.stages["render"] for p in run.curve.points]
    height, width = buffer.shape
    return FixedCosts(label, width * height / 1e6, ms, iteration_ms, render_ms, denoiser.config.oidn_candidate)
