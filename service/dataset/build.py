"""Render the training data set: noisy inputs at several sample counts plus a reference.

Every frame of every procedural scene is rendered with the project's own renderer, so the
inputs carry exactly the statistics the loop produces:

- one FrameBuffer accumulated uniformly 16 → 32 → 64 → 128 spp, written at each level;
- a branch copied after the 16-spp pass that continues like the adaptive loop does (each
  iteration doubles the total, spent ∝ relative variance — the error network does not exist
  yet when the data is made, and variance is the loop's own fallback allocator);
- an independent high-spp reference (its own seed: a reference that shared samples with the
  input would reward the denoiser for copying noise);
- with `loop_networks` (`renderloop dataset --loop-branch`), a third branch from the 16-spp
  buffer that runs the render loop's own steps — denoise, predict the error, allocate by it,
  render — so the error network can be trained on exactly what the loop feeds it: the shipped
  denoiser's output on the loop's non-uniform sample counts, at every iteration's budget.

Layout: DIR/<split>/scene_<seed>/frame_<f>/<item>.exr, DIR/manifest.json. Resumable: an item
whose EXR is already there and readable is not written again; files are written under a
temporary name and renamed, so an interrupted write never looks finished.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from models.pretrained import Networks
from service.atomic import atomic_write, atomic_write_text
from service.dataset.procedural import DATASET_LAYOUTS, SceneSpec, sample_spec, scene_dict, sensor_dict
from service.dataset.splits import SPLITS, scene_seeds
from service.exr import ExrError, ExrFrame, read_exr, write_exr
from service.loop.allocate import allocate_samples, exposed_relative_variance, iteration_budget, variance_weights
from service.loop.denoise_session import DenoiseSession
from service.loop.loop import converged_error, next_counts
from service.render.framebuffer import FrameBuffer
from service.render.renderer import render_samples
from service.render.runtime import mitsuba

# (item, samples per pixel added) in order; the totals double like the loop's iterations.
UNIFORM_STEPS = (("spp16", 16), ("spp32", 16), ("spp64", 32), ("spp128", 64))
# The adaptive branch starts from the 16-spp buffer; each step adds as many samples as the
# buffer holds (the loop's doubling rule), handed out per pixel.
ADAPTIVE_ITEMS = ("adaptive32", "adaptive64")
REFERENCE = "reference"
ITEMS = tuple(name for name, _ in UNIFORM_STEPS) + ADAPTIVE_ITEMS + (REFERENCE,)
INPUT_ITEMS = ITEMS[:-1]
# The loop branch (optional): the 16-spp buffer continued by the loop's own error allocator.
LOOP_ITEMS = ("loop32", "loop64", "loop128")
MANIFEST = "manifest.json"
FORMAT = "renderloop-dataset"
FORMAT_VERSION = 1
# Settings that decide what a finished item contains: resuming with other values would mix
# incompatible files under the same names.
FIXED_SETTINGS = ("size", "frames", "seed", "reference_spp", "layout")
# What a manifest written before a setting existed was built with.
_SETTING_BEFORE_RECORDED = {"layout": "mixed"}
# Seed streams per frame, so inputs, the adaptive branch and the reference never share samples.
_STREAM_UNIFORM, _STREAM_ADAPTIVE, _STREAM_REFERENCE, _STREAM_LOOP = 0, 1, 2, 3
# The loop branch's allocation rounding draws from its own seeds, apart from the adaptive branch's.
LOOP_ROUNDING_STREAM = 100


class DatasetError(ValueError):
    """Bad data-set settings or an output folder built with other settings."""


@dataclass(frozen=True)
class DatasetSettings:
    scenes: int
    size: int
    frames: int
    seed: int
    split: str
    reference_spp: int
    loop_branch: bool = False
    layout: str = "mixed"  # "mixed": each seed draws its layout; or one of procedural's layouts for all

    @property
    def items(self) -> tuple[str, ...]:
        return ITEMS + LOOP_ITEMS if self.loop_branch else ITEMS

    def validate(self) -> None:
        """Raise DatasetError with a one-line message for the first bad value."""
        checks = (
            (self.scenes >= 1, f"--scenes must be >= 1, got {self.scenes}"),
            (8 <= self.size <= 4096, f"--size must be in [8, 4096], got {self.size}"),
            (1 <= self.frames <= 64, f"--frames must be in [1, 64], got {self.frames}"),
            (self.seed >= 0, f"--seed must be >= 0, got {self.seed}"),
            (self.split in SPLITS, f"--split must be one of {', '.join(SPLITS)}, got {self.split!r}"),
            (self.reference_spp >= 1, f"--reference-spp must be >= 1, got {self.reference_spp}"),
            (self.layout in DATASET_LAYOUTS,
             f"--layout must be one of {', '.join(DATASET_LAYOUTS)}, got {self.layout!r}"),
        )
        for ok, message in checks:
            if not ok:
                raise DatasetError(message)

    def command(self, out_dir: Path) -> str:
        """The CLI command that (re)builds exactly this data set."""
        return (f"renderloop dataset -o {out_dir} --scenes {self.scenes} --size {self.size} "
                f"--frames {self.frames} --seed {self.seed} --split {self.split} "
                f"--reference-spp {self.reference_spp}" + (" --loop-branch" if self.loop_branch else "")
                + (f" --layout {self.layout}" if self.layout != "mixed" else ""))

    @property
    def spec_layout(self) -> str | None:
        """sample_spec's `layout`: None lets each seed draw its own."""
        return None if self.layout == "mixed" else self.layout


def frame_dir(root: Path, split: str, scene_seed: int, frame: int) -> Path:
    return Path(root) / split / f"scene_{scene_seed}" / f"frame_{frame}"


def item_path(root: Path, split: str, scene_seed: int, frame: int, item: str) -> Path:
    return frame_dir(root, split, scene_seed, frame) / f"{item}.exr"


def is_finished(path: Path) -> bool:
    """True when `path` is a complete, readable EXR (a torn file fails to read)."""
    try:
        read_exr(path)
    except ExrError:
        return False
    return True


def _write_atomic(path: Path, frame: ExrFrame) -> None:
    atomic_write(path, lambda tmp: write_exr(tmp, frame))


def render_seed(scene_seed: int, frame: int, stream: int) -> int:
    """A 32-bit renderer seed per (scene, frame, stream), well mixed by SeedSequence."""
    return int(np.random.SeedSequence([scene_seed, frame + 1, stream]).generate_state(1)[0])


# --- rendering one frame ---------------------------------------------------------------------


@dataclass
class _FrameJob:
    """What one frame needs: its loaded scene, the previous camera (sequences) and its paths."""

    scene_seed: int
    frame: int
    scene: object
    prev_sensor: object | None
    paths: dict[str, Path]
    missing: set[str]
    networks: Networks | None = None  # drives the loop branch


def _exr_frame(buffer: FrameBuffer, scene_seed: int, iteration: int, *, color: np.ndarray | None = None) -> ExrFrame:
    mean = buffer.mean
    return ExrFrame(
        color=mean if color is None else color,
        noisy=mean,
        variance=buffer.variance,
        albedo=buffer.albedo,
        normal=buffer.normal,
        depth=buffer.depth,
        motion=buffer.motion,
        spp=buffer.spp.astype(np.uint32),
        header={"scene": f"procedural-{scene_seed}", "iteration": iteration,
                "total_samples": int(buffer.spp.sum()), "variant": mitsuba().variant()},
    )


def _render(job: _FrameJob, buffer: FrameBuffer, counts: np.ndarray, stream: int) -> None:
    render_samples(job.scene, counts, buffer, seed=render_seed(job.scene_seed, job.frame, stream),
                   prev_sensor=job.prev_sensor, splat=False)  # training reads the per-pixel estimates only


def _save(job: _FrameJob, item: str, frame: ExrFrame) -> None:
    if item in job.missing:
        _write_atomic(job.paths[item], frame)


def _adaptive_branch(job: _FrameJob, start: FrameBuffer) -> None:
    """Continue a copy of the 16-spp buffer the way the loop's variance allocator would."""
    buffer = start.copy()
    for iteration, item in enumerate(ADAPTIVE_ITEMS, start=1):
        budget = int(buffer.spp.sum())  # doubling: this iteration adds what is there already
        weights = variance_weights(exposed_relative_variance(buffer.mean, buffer.variance))
        counts = allocate_samples(weights, budget, seed=render_seed(job.scene_seed, job.frame, iteration))
        _render(job, buffer, counts, _STREAM_ADAPTIVE)
        _save(job, item, _exr_frame(buffer, job.scene_seed, iteration))


def _loop_branch(job: _FrameJob, start: FrameBuffer) -> None:
    """Continue a copy of the 16-spp buffer with the render loop's own steps (single frame,
    λ = 1): denoise, predict the error, zero it where samples agree, allocate ∝ error."""
    buffer = start.copy()
    session = DenoiseSession(job.networks, frames=1, temporal_radius=0)
    lam = np.ones(buffer.shape, dtype=np.float32)
    for iteration, item in enumerate(LOOP_ITEMS, start=1):
        error = session.predict_error(session.denoise([buffer], lam))[0]  # keyed by frame index
        counts = next_counts("error", buffer, converged_error(buffer.converged(), error),
                             iteration_budget(int(buffer.spp.sum())),
                             seed=render_seed(job.scene_seed, job.frame, LOOP_ROUNDING_STREAM + iteration))
        _render(job, buffer, counts, _STREAM_LOOP)
        _save(job, item, _exr_frame(buffer, job.scene_seed, iteration))


def _render_inputs(job: _FrameJob, shape: tuple[int, int]) -> None:
    """The uniform levels and the adaptive (and loop) branches; skipped entirely when all exist."""
    if not job.missing.intersection(INPUT_ITEMS + LOOP_ITEMS):
        return
    buffer = FrameBuffer.empty(*shape)
    for iteration, (item, added) in enumerate(UNIFORM_STEPS):
        _render(job, buffer, np.full(shape, added), _STREAM_UNIFORM)
        _save(job, item, _exr_frame(buffer, job.scene_seed, iteration))
        if iteration == 0 and job.missing.intersection(ADAPTIVE_ITEMS):
            _adaptive_branch(job, buffer)
        if iteration == 0 and job.missing.intersection(LOOP_ITEMS):
            _loop_branch(job, buffer)
        if not job.missing.intersection(name for name, _ in UNIFORM_STEPS[iteration + 1:]):
            break  # later levels exist already; the samples to reach them are not needed


def _render_reference(job: _FrameJob, shape: tuple[int, int], spp: int) -> None:
    if REFERENCE not in job.missing:
        return
    buffer = FrameBuffer.empty(*shape)
    _render(job, buffer, np.full(shape, spp), _STREAM_REFERENCE)
    _save(job, REFERENCE, _exr_frame(buffer, job.scene_seed, 0))


def _frame_job(root: Path, settings: DatasetSettings, spec: SceneSpec, frame: int,
               networks: Networks | None = None) -> _FrameJob:
    mi = mitsuba()
    paths = {item: item_path(root, settings.split, spec.seed, frame, item) for item in settings.items}
    missing = {item for item, path in paths.items() if not is_finished(path)}
    scene = prev_sensor = None
    if missing:
        scene = mi.load_dict(scene_dict(spec, size=settings.size, frame=frame))
        if settings.frames > 1:
            # Frame −1 exists on the camera path, so frame 0 of a sequence has motion too.
            prev_sensor = mi.load_dict(sensor_dict(spec.camera, size=settings.size, frame=frame - 1))
    return _FrameJob(spec.seed, frame, scene, prev_sensor, paths, missing, networks)


def render_frame(root: Path, settings: DatasetSettings, spec: SceneSpec, frame: int,
                 networks: Networks | None = None) -> dict[str, Path]:
    """Render and write whatever items of (scene, frame) are missing; returns all item paths.
    `networks` drive the loop branch (settings.loop_branch)."""
    job = _frame_job(root, settings, spec, frame, networks)
    shape = (settings.size, settings.size)
    if job.missing:
        _render_inputs(job, shape)
        _render_reference(job, shape, settings.reference_spp)
    return job.paths


# --- manifest --------------------------------------------------------------------------------


def read_manifest(root: Path) -> dict:
    """The manifest of data set `root`; an empty one for a new folder."""
    path = Path(root) / MANIFEST
    if not path.is_file():
        return {"format": FORMAT, "version": FORMAT_VERSION, "items": list(ITEMS), "splits": {}}
    try:
        manifest = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{path}: not valid JSON ({exc})") from exc
    if manifest.get("format") != FORMAT or manifest.get("version") != FORMAT_VERSION:
        raise DatasetError(f"{path}: not a {FORMAT} v{FORMAT_VERSION} manifest")
    return manifest


def _write_manifest(root: Path, manifest: dict) -> None:
    path = Path(root) / MANIFEST
    atomic_write_text(path, json.dumps(manifest, indent=1))


def _check_compatible(root: Path, manifest: dict, settings: DatasetSettings) -> None:
    previous = manifest["splits"].get(settings.split)
    if previous is None:
        return
    for key in FIXED_SETTINGS:
        built = previous.get(key, _SETTING_BEFORE_RECORDED.get(key))
        if built != getattr(settings, key):
            raise DatasetError(
                f"{root}/{settings.split} was built with {key}={built}, not "
                f"{getattr(settings, key)}; use another --out folder or the same settings"
            )


def _split_entry(root: Path, settings: DatasetSettings, seeds: list[int], complete: bool) -> dict:
    entries = [
        {"scene": seed, "frame": frame,
         "items": {item: str(item_path(Path(), settings.split, seed, frame, item)) for item in settings.items}}
        for seed in seeds for frame in range(settings.frames)
    ]
    return {**asdict(settings), "scene_seeds": seeds, "command": settings.command(root),
            "complete": complete, "entries": entries}


# --- the whole data set ----------------------------------------------------------------------


def build_dataset(
    out_dir: str | Path,
    *,
    scenes: int,
    size: int,
    frames: int,
    seed: int,
    split: str = "train",
    reference_spp: int = 1024,
    progress: bool = True,
    loop_networks: Networks | None = None,
    layout: str = "mixed",
) -> Path:
    """Render `scenes` procedural scenes × `frames` frames into `out_dir`; returns the manifest path.

    Safe to re-run: finished items are skipped, so an interrupted build resumes, and a larger
    `scenes` with the same seed extends the data set (scene seeds are prefix-stable). `layout`:
    "mixed" lets each seed draw its own; a layout name gives every scene that one.
    """
    settings = DatasetSettings(scenes=scenes, size=size, frames=frames, seed=seed, split=split,
                               reference_spp=reference_spp, loop_branch=loop_networks is not None,
                               layout=layout)
    settings.validate()
    if settings.loop_branch and frames != 1:
        raise DatasetError("--loop-branch renders single frames (the error network sees one frame); use --frames 1")
    root = Path(out_dir)
    if root.exists() and not root.is_dir():
        raise DatasetError(f"--out {root} exists and is not a folder")
    root.mkdir(parents=True, exist_ok=True)
    manifest = read_manifest(root)
    _check_compatible(root, manifest, settings)
    seeds = scene_seeds(split, scenes, seed)
    # Recorded before rendering, so an interrupted build is still checked on resume.
    manifest["splits"][split] = _split_entry(root, settings, seeds, complete=False)
    _write_manifest(root, manifest)
    with tqdm(total=scenes * frames, unit="frame", desc=f"dataset {split}", disable=not progress) as bar:
        for scene_seed in seeds:
            spec = sample_spec(scene_seed, settings.spec_layout)
            for frame in range(frames):
                bar.set_postfix(scene=scene_seed, frame=frame)
                render_frame(root, settings, spec, frame, loop_networks)
                bar.update(1)
    manifest["splits"][split]["complete"] = True
    _write_manifest(root, manifest)
    return root / MANIFEST
