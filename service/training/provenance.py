"""What a checkpoint records about how it was made (models.checkpoint's RECIPE_KEY, DATA_KEY):
the recipe's short name and one hash of the data sets it trained on, plus the stage, and the
weights it started from by content. No paths: a file made on one machine reads the same on any
other (the recipe's commands are in scripts/train-weights.sh and docs/models.md).

The data hash reads each data set's manifest (service/dataset/build.py) and keeps what decides
its contents: per split the build settings and the scene seeds, not the folder it was written
to nor whether the build finished. Two folders built by the same `renderloop dataset` command
hash alike; the same data sets named in another order do not (the trainer samples in order)."""
from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path
from typing import Iterable

from models.checkpoint import DATA_KEY, RECIPE_KEY
from service.dataset.build import DatasetSettings, read_manifest
from service.dataset.splits import scene_seeds

_SETTINGS = tuple(f.name for f in dataclasses.fields(DatasetSettings))


def split_fingerprint(entry: dict) -> dict:
    """One manifest split → its build settings and scene seeds."""
    return {**{name: entry.get(name) for name in _SETTINGS}, "scene_seeds": list(entry.get("scene_seeds", []))}


def manifest_fingerprint(manifest: dict) -> dict:
    return {split: split_fingerprint(entry) for split, entry in sorted(manifest.get("splits", {}).items())}


def fingerprints_hash(fingerprints: Iterable[dict]) -> str:
    text = json.dumps(list(fingerprints), sort_keys=True, separators=(",", ":"))
    return "sha256:" + hashlib.sha256(text.encode()).hexdigest()[:16]


def data_hash(roots: Iterable[str | Path]) -> str:
    """The hash of the data sets in `roots` (in order), from their manifests."""
    return fingerprints_hash(manifest_fingerprint(read_manifest(Path(root))) for root in roots)


def planned_data_hash(builds: Iterable[DatasetSettings]) -> str:
    """The hash `data_hash` gives the folders these builds write (one split each), without
    rendering them: for a checkpoint whose data sets are not on this machine."""
    return fingerprints_hash({s.split: split_fingerprint({**dataclasses.asdict(s),
                                                          "scene_seeds": scene_seeds(s.split, s.scenes, s.seed)})}
                             for s in builds)


def file_digest(path: str | Path) -> str:
    return "sha1:" + hashlib.sha1(Path(path).read_bytes()).hexdigest()[:10]


def provenance(recipe: str, data_roots: Iterable[str | Path], stage: str, init: Path | None = None) -> dict:
    """A checkpoint's `extra`: recipe, data hash, stage and (when fine-tuned) the starting file's digest."""
    extra = {RECIPE_KEY: recipe, DATA_KEY: data_hash(data_roots), "stage": stage}
    if init is not None:
        extra["init"] = file_digest(init)
    return extra
