"""What an uneven pass of a scene with a stratifying sampler costs against the same pass of the
same scene with the `independent` sampler (docs/sampler.md, "Uneven stratified passes").

A stratifying scene's pass is traced in digit groups (service/render/stratified_lanes.py): one
trace and one kernel launch per sequence length present in the count map, each ~30 ms of Python
tracing and kernel assembly on the LLVM backend whatever its size, where an independent pass is
one launch. The counts are what the loop's later iterations hand out: the loop's allocator
(service/loop/allocate.py, its defaults) on a log-normal error map, the pass's mean spp equal to
the spp before it (the loop doubles the total). Both scenes run the same count maps, interleaved,
median of the repeats.
"""
from __future__ import annotations

import re
import shutil
import statistics
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.loop.allocate import allocate_samples
from service.render.framebuffer import FrameBuffer
from service.render.renderer import render_samples
from service.render.scenes import load_scene

SCENES_DIR = Path(__file__).resolve().parent.parent / "scenes" / "dev"
# (scene, film side, prior spp of each pass): the loop's 2nd–4th iterations at 128², its 2nd at 512².
CASES = (("fine_texture", 128, (16, 32, 64)), ("dof_desk", 128, (16, 32, 64)),
         ("fine_texture", 512, (16,)), ("dof_desk", 512, (16,)))
# Spread of the log error map the counts follow (σ of its log): a map whose hardest pixels hit
# the allocator's 8× cap, as the loop's error maps do on scenes/dev.
ERROR_LOG_SPREAD = 1.0


@dataclass(frozen=True)
class StratifiedPassRow:
    scene: str
    size: int
    prior_spp: int
    mean_spp: float        # of the pass
    max_spp: int
    launches: int          # kernel launches of the stratified pass (one per sequence length and chunk)
    stratified_s: float    # median seconds of the stratified pass
    independent_s: float   # the same counts with the `independent` sampler

    @property
    def ratio(self) -> float:
        return self.stratified_s / self.independent_s


def loop_like_counts(size: int, mean_spp: int, rng: np.random.Generator) -> np.ndarray:
    """A later iteration's count map: the loop's allocator on a log-normal error map."""
    weights = np.exp(rng.normal(0.0, ERROR_LOG_SPREAD, (size, size)))
    return allocate_samples(weights, mean_spp * size * size)


def independent_copy(scene_xml: Path, folder: Path) -> Path:
    """The scene's folder copied into `folder` with its sampler's type set to `independent`."""
    shutil.copytree(scene_xml.parent, folder, dirs_exist_ok=True)
    text = scene_xml.read_text()
    text = re.sub(r'<sampler type="[^"]*"', '<sampler type="independent"', text)
    copy = folder / scene_xml.name
    copy.write_text(text)
    return copy


def _pass_seconds(scene, prior: int, counts: np.ndarray, seed: int) -> tuple[float, int]:
    """Seconds and chunks of one pass of `counts` after `prior` uniform spp."""
    buffer = FrameBuffer.empty(*counts.shape)
    buffer.spp[...] = prior
    start = time.perf_counter()
    result = render_samples(scene, counts, buffer, seed=seed)
    return time.perf_counter() - start, result.chunks


def case_rows(name: str, size: int, priors: tuple[int, ...], repeats: int) -> list[StratifiedPassRow]:
    """One scene at one film size: each pass timed with its own sampler and with `independent`."""
    scene_xml = SCENES_DIR / name / "scene.xml"
    with tempfile.TemporaryDirectory() as folder:
        stratified = load_scene(scene_xml, width=size, height=size)
        independent = load_scene(independent_copy(scene_xml, Path(folder) / name), width=size, height=size)
    rng = np.random.default_rng(0)
    rows = []
    for prior in priors:
        counts = loop_like_counts(size, prior, rng)
        for scene in (stratified, independent):  # kernels are compiled (and cached) on first use
            _pass_seconds(scene, prior, counts, 0)
        times: dict[str, list[float]] = {"stratified": [], "independent": []}
        launches = 0
        for rep in range(repeats):
            seconds, launches = _pass_seconds(stratified, prior, counts, rep + 1)
            times["stratified"].append(seconds)
            times["independent"].append(_pass_seconds(independent, prior, counts, rep + 1)[0])
        rows.append(StratifiedPassRow(name, size, prior, float(counts.mean()), int(counts.max()), launches,
                                      statistics.median(times["stratified"]),
                                      statistics.median(times["independent"])))
    return rows


def stratified_pass_rows(repeats: int = 5, cases=CASES) -> list[StratifiedPassRow]:
    return [row for name, size, priors in cases for row in case_rows(name, size, priors, repeats)]


def stratified_pass_table(rows: list[StratifiedPassRow]) -> str:
    lines = ["| scene | film | spp before → pass mean (max) | launches | stratified s | independent s "
             "| stratified ÷ independent |",
             "|---|---|---|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r.scene} | {r.size}² | {r.prior_spp} → {r.mean_spp:.0f} ({r.max_spp}) | {r.launches} | "
                     f"{r.stratified_s:.3f} | {r.independent_s:.3f} | **{r.ratio:.2f}×** |")
    return "\n".join(lines)



def report_fields(rows: list[StratifiedPassRow]) -> dict[str, object]:
    """The stratified-pass section of docs/sampler.md (bench/templates/sampler.md)."""
    return {"stratified_table": stratified_pass_table(rows)}
