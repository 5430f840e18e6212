"""The loop benchmark's figures: error vs time per scene, sample-count maps, predicted vs true
error maps. matplotlib is a dev dependency, so the plots are optional: without it the report
says so and carries its tables alone.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from bench.common import true_error_map
from bench.report_images import save_figure
from bench.loop_run import PRODUCT, Headline, SceneResult
from service.images import linear_to_srgb

try:  # optional: a dev dependency; the report notes when the plots are missing
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter
except ImportError:
    plt = None


def write_plots(results: list[SceneResult], head: Headline, folder: Path) -> list[Path]:
    """Error vs time (log-log) per scene, sample-count maps, predicted vs true error maps."""
    if plt is None:
        return []

    folder.mkdir(parents=True, exist_ok=True)
    n = len(results)
    paths = []

    fig, axes = plt.subplots(1, n, figsize=(3.2 * n, 3.0), squeeze=False)
    for ax, result in zip(axes[0], results):
        for key, run in result.runs.items():
            ax.loglog([r.cumulative_seconds for r in run.rows], [r.metrics["smape"] for r in run.rows],
                      marker="o", markersize=3, label=f"({key})")
        ax.axhline(head.target[result.scene.label], color="grey", linestyle=":", linewidth=1)
        ax.set_title(result.scene.label, fontsize=8)
        ax.set_xlabel("cumulative wall time [s]", fontsize=7)
        ax.tick_params(which="both", labelsize=6)
        for axis in (ax.xaxis, ax.yaxis):  # 1-2-5 labels: readable within one decade and across several
            axis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
            axis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
            axis.set_minor_formatter(NullFormatter())
    axes[0][0].set_ylabel("SMAPE", fontsize=7)
    axes[0][0].legend(fontsize=6)
    paths.append(_save(fig, folder / "error_vs_time.png"))

    fig, axes = plt.subplots(n, 4, figsize=(8.0, 2.1 * n), squeeze=False)
    for row, result in zip(axes, results):
        c, d = result.runs.get("c"), result.runs[PRODUCT]
        vmax = max(float(d.spp_map.max()), float(c.spp_map.max()) if c else 0.0)
        panels = [(linear_to_srgb(result.reference), "reference", None), (linear_to_srgb(d.image), "(d) image", None),
                  (c.spp_map if c else np.zeros_like(d.spp_map), "(c) spp", vmax), (d.spp_map, "(d) spp", vmax)]
        for ax, (image, title, top) in zip(row, panels):
            shown = ax.imshow(image, vmin=0 if top else None, vmax=top, cmap="magma" if top else None,
                              interpolation="nearest")
            if top:
                fig.colorbar(shown, ax=ax, fraction=0.046)
            ax.set_title(f"{result.scene.label}: {title}", fontsize=6)
            ax.axis("off")
    paths.append(_save(fig, folder / "spp_maps.png", dpi=72))

    fig, axes = plt.subplots(n, 2, figsize=(4.6, 2.1 * n), squeeze=False)
    for row, result in zip(axes, results):
        d = result.runs[PRODUCT]
        true = true_error_map(d.image, result.reference)
        top = float(np.percentile(true, 99)) or 1.0
        for ax, (image, title) in zip(row, [(d.predicted_error, "predicted SMAPE"), (true, "true SMAPE")]):
            shown = ax.imshow(image, vmin=0, vmax=top, cmap="viridis", interpolation="nearest")
            fig.colorbar(shown, ax=ax, fraction=0.046)
            ax.set_title(f"{result.scene.label}: (d) {title}", fontsize=6)
            ax.axis("off")
    paths.append(_save(fig, folder / "error_maps.png", dpi=72))
    return paths


def _save(fig, path: Path, dpi: int = 90) -> Path:
    fig.tight_layout()
    save_figure(fig, path, dpi=dpi, pil_kwargs={"optimize": True})  # small PNGs, rewritten only when changed
    plt.close(fig)
    return path

