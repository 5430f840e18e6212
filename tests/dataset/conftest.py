"""Tiny data sets built once per session: rendering is the slow part of these tests."""
from __future__ import annotations

from pathlib import Path

import pytest

TINY = dict(size=16, seed=0, reference_spp=64, progress=False)


@pytest.fixture(scope="session")
def tiny() -> dict:
    """The build settings both fixtures use (size, seed, reference spp, no progress bar)."""
    return dict(TINY)


@pytest.fixture(scope="session")
def sequence_dataset(tmp_path_factory) -> Path:
    """2 scenes × 3 frames (camera paths with motion), train split."""
    from service.dataset.build import build_dataset

    root = tmp_path_factory.mktemp("sequence")
    build_dataset(root, scenes=2, frames=3, split="train", **TINY)
    return root


@pytest.fixture(scope="session")
def still_dataset(tmp_path_factory) -> Path:
    """2 single-frame scenes, held-out split."""
    from service.dataset.build import build_dataset

    root = tmp_path_factory.mktemp("still")
    build_dataset(root, scenes=2, frames=1, split="heldout", **TINY)
    return root
