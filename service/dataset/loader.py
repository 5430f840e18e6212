"""A torch Dataset over a built data set: noisy frame windows and their references, cropped.

One item is (scene, window of 2M+1 consecutive frames, input level such as `spp16` or
`adaptive32`). The whole window is cut with the same crop, so motion vectors still point at
the matching pixels of the neighbours. Crops are drawn from (seed, epoch, index): the same
run sees the same crops whatever the number of DataLoader workers.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import Dataset

from models.frames import FrameTensors
from service.dataset.build import INPUT_ITEMS, LOOP_ITEMS, REFERENCE, DatasetError, read_manifest
from service.exr import ExrFrame, read_exr
from service.loop.oidn import oidn_image

# ExrFrame layers → FrameTensors fields of the noisy input (the input's colour is its mean).
_INPUT_LAYERS = {"color": "noisy", "variance": "variance", "albedo": "albedo", "normal": "normal",
                 "depth": "depth", "motion": "motion", "spp": "spp"}


@dataclass(frozen=True)
class WindowItem:
    """One training item: the frame files of a window, at one input level."""

    scene: int
    frames: tuple[int, ...]  # consecutive frame indices, oldest first
    level: str  # one of INPUT_ITEMS or LOOP_ITEMS
    inputs: tuple[Path, ...]  # per frame: the noisy EXR
    references: tuple[Path, ...]  # per frame: reference.exr


@dataclass
class TrainingSample:
    """A cropped window: `noisy` and `reference` are (T, C, h, w); frame `centre` is denoised."""

    noisy: FrameTensors
    reference: Tensor
    centre: int
    key: str  # "scene/frames/level@y,x", for logs and debugging
    candidate: Tensor | None = None  # (C, h, w) OIDN on the whole centre frame, cropped


@dataclass
class TrainingBatch:
    """Collated samples: one FrameTensors (B, C, h, w) and one reference per window position."""

    frames: list[FrameTensors]
    references: list[Tensor]
    centre: int
    keys: list[str]
    candidates: Tensor | None = None  # (B, C, h, w) when the data set serves candidate images


def window_items(root: str | Path, split: str, radius: int, levels: tuple[str, ...]) -> list[WindowItem]:
    """Every full window of 2·radius+1 frames, per scene and level, from the manifest."""
    root = Path(root)
    manifest = read_manifest(root)
    entry = manifest["splits"].get(split)
    if entry is None:
        raise DatasetError(f"{root} has no {split!r} split; build it with renderloop dataset --split {split}")
    unknown = set(levels) - set(INPUT_ITEMS + LOOP_ITEMS)
    if unknown:
        raise DatasetError(f"unknown input levels {sorted(unknown)}; known: {', '.join(INPUT_ITEMS + LOOP_ITEMS)}")
    absent = set(levels) - set(entry["entries"][0]["items"]) if entry["entries"] else set()
    if absent:
        raise DatasetError(f"{root}/{split} has no {', '.join(sorted(absent))} inputs; the loop levels come from "
                           f"`renderloop dataset --loop-branch`")
    span = 2 * radius + 1
    if entry["frames"] < span:
        raise DatasetError(f"{root}/{split} has {entry['frames']} frames per scene; a window of "
                           f"radius {radius} needs {span}")
    files = {(e["scene"], e["frame"]): e["items"] for e in entry["entries"]}
    items = []
    for scene in entry["scene_seeds"]:
        for first in range(entry["frames"] - span + 1):
            frames = tuple(range(first, first + span))
            for level in levels:
                inputs = tuple(root / files[scene, f][level] for f in frames)
                references = tuple(root / files[scene, f][REFERENCE] for f in frames)
                if all(p.is_file() for p in inputs + references):  # an unfinished build: skip
                    items.append(WindowItem(scene, frames, level, inputs, references))
    return items


def _chw(array: np.ndarray) -> np.ndarray:
    """(H, W, C) or (H, W) → (C, H, W) float32."""
    array = np.asarray(array, dtype=np.float32)
    return (array[None] if array.ndim == 2 else array.transpose(2, 0, 1)).copy()


def _crop(array: np.ndarray, corner: tuple[int, int], crop: tuple[int, int]) -> np.ndarray:
    (y, x), (h, w) = corner, crop
    return array[..., y:y + h, x:x + w]


class DenoiserDataset(Dataset):
    """Items of `window_items` (of one data set or several together), read from EXR (decoded
    files cached in memory) and cropped.

    crop: side of the square crop, or None for whole frames. radius: M of the 2M+1 window
    (0 = single frame). levels: which noisy inputs to use (default all of them).
    """

    def __init__(self, root: str | Path | Sequence[str | Path], *, split: str = "train",
                 levels: tuple[str, ...] = INPUT_ITEMS, radius: int = 0, crop: int | None = 64, seed: int = 0,
                 cache: bool = True, candidate: bool = False) -> None:
        if radius < 0:
            raise DatasetError(f"window radius must be >= 0, got {radius}")
        roots = [root] if isinstance(root, (str, Path)) else list(root)
        self.items = [item for r in roots for item in window_items(r, split, radius, tuple(levels))]
        if not self.items:
            raise DatasetError(f"{', '.join(map(str, roots))}/{split} has no finished items for levels {list(levels)}")
        self.crop, self.seed, self.radius, self.epoch = crop, seed, radius, 0
        self.candidate = candidate  # serve OIDN on the centre frame (the denoiser's oidn_candidate)
        self._cache: dict[Path, dict[str, np.ndarray | None]] | None = {} if cache else None
        self._check_crop(read_exr(self.items[0].inputs[0]).shape)

    def _check_crop(self, shape: tuple[int, int]) -> None:
        if self.crop is not None and not 1 <= self.crop <= min(shape):
            raise DatasetError(f"crop {self.crop} does not fit frames of {shape[1]}x{shape[0]}")

    def set_epoch(self, epoch: int) -> None:
        """New crops each epoch, still reproducible from (seed, epoch)."""
        self.epoch = epoch

    def __len__(self) -> int:
        return len(self.items)

    def _layers(self, path: Path) -> dict[str, np.ndarray | None]:
        """The layers of one EXR as CHW arrays (cached: the data set is small, decoding is not free)."""
        if self._cache is not None and path in self._cache:
            return self._cache[path]
        frame: ExrFrame = read_exr(path)
        layers = {name: None if getattr(frame, attr) is None else _chw(getattr(frame, attr))
                  for name, attr in _INPUT_LAYERS.items()}
        layers["reference"] = _chw(frame.color)
        if self._cache is not None:
            self._cache[path] = layers
        return layers

    def _candidate(self, path: Path) -> np.ndarray:
        """OIDN on the whole frame (CHW), computed once per file: OIDN sees the full image, as in
        the service, not the crop."""
        layers = self._layers(path)
        if "candidate" not in layers:
            hwc = {name: layers[name].transpose(1, 2, 0) for name in ("color", "albedo", "normal")}
            layers["candidate"] = _chw(oidn_image(hwc["color"], hwc["albedo"], hwc["normal"]))
        return layers["candidate"]

    def _corner(self, index: int, shape: tuple[int, int]) -> tuple[int, int]:
        if self.crop is None:
            return 0, 0
        rng = np.random.default_rng([self.seed, self.epoch, index])
        return int(rng.integers(shape[0] - self.crop + 1)), int(rng.integers(shape[1] - self.crop + 1))

    def __getitem__(self, index: int) -> TrainingSample:
        item = self.items[index]
        inputs = [self._layers(p) for p in item.inputs]
        shape = inputs[0]["color"].shape[1:]
        crop = shape if self.crop is None else (self.crop, self.crop)
        corner = self._corner(index, shape)

        def stack(layers: list[dict], name: str) -> Tensor | None:
            if any(layer[name] is None for layer in layers):
                return None
            return torch.from_numpy(np.stack([_crop(layer[name], corner, crop) for layer in layers]))

        noisy = FrameTensors(**{name: stack(inputs, name) for name in _INPUT_LAYERS})
        references = [self._layers(p) for p in item.references]
        key = f"{item.scene}/{item.frames[0]}-{item.frames[-1]}/{item.level}@{corner[0]},{corner[1]}"
        candidate = None
        if self.candidate:
            candidate = torch.from_numpy(np.ascontiguousarray(_crop(self._candidate(item.inputs[self.radius]), corner, crop)))
        return TrainingSample(noisy=noisy, reference=stack(references, "reference"), centre=self.radius, key=key,
                              candidate=candidate)


def collate_samples(samples: list[TrainingSample]) -> TrainingBatch:
    """DataLoader collate_fn: window position t of every sample → one (B, C, h, w) FrameTensors."""
    steps = samples[0].noisy.color.shape[0]

    def batch(t: int) -> FrameTensors:
        return samples[0].noisy.map(
            lambda name, _: torch.stack([getattr(s.noisy, name)[t] for s in samples]))

    return TrainingBatch(
        frames=[batch(t) for t in range(steps)],
        references=[torch.stack([s.reference[t] for s in samples]) for t in range(steps)],
        centre=samples[0].centre,
        keys=[s.key for s in samples],
        candidates=None if samples[0].candidate is None else torch.stack([s.candidate for s in samples]),
    )
