"""A report's re-run rewrites a figure only when the picture changed (bench/report_images.py)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from bench.report_images import save_figure
from required_components import import_component

plt = import_component("matplotlib", "matplotlib.pyplot")


def draw(image: np.ndarray, path: Path) -> bytes:
    fig, ax = plt.subplots(figsize=(3, 3))
    ax.imshow(image, cmap="magma", vmin=0, vmax=1, interpolation="nearest")
    ax.axis("off")
    save_figure(fig, path, dpi=80)
    plt.close(fig)
    return path.read_bytes()


def picture(seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).random((48, 48))


def test_a_redrawn_figure_that_differs_only_by_run_to_run_noise_keeps_the_committed_file(tmp_path: Path) -> None:
    path = tmp_path / "scene.png"
    first = draw(picture(), path)
    noisy = picture() + np.random.default_rng(1).normal(0, 1e-3, (48, 48))  # a last-bits difference
    assert draw(np.clip(noisy, 0, 1), path) == first


def test_a_figure_that_shows_something_new_is_rewritten(tmp_path: Path) -> None:
    path = tmp_path / "scene.png"
    first = draw(picture(), path)
    changed = picture().copy()
    changed[10:30, 10:30] = 1 - changed[10:30, 10:30]  # a region visibly different
    assert draw(changed, path) != first


def test_a_figure_of_another_size_is_rewritten(tmp_path: Path) -> None:
    path = tmp_path / "scene.png"
    draw(picture(), path)
    fig, ax = plt.subplots(figsize=(4, 3))
    ax.imshow(picture(), cmap="magma", vmin=0, vmax=1)
    save_figure(fig, path, dpi=80)
    plt.close(fig)
    with Image.open(path) as written:
        assert written.size == (320, 240)
