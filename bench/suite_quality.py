"""The measurements of `renderloop bench --denoiser --suite dev` (the report is
bench/suite_quality_report.py): the denoiser against OIDN on the hand-written
development scenes (never trained on), at 16, 64 and 256 spp, against their committed references.

Per scene and sample count: one uniform render (its own pass, seeded), denoised by our KPCN
(single frame, λ = 1) and by OIDN on the same noisy colour, albedo and normal; SMAPE, relMSE,
PSNR and the energy ratio (mean radiance ÷ the reference's) for noisy / KPCN / OIDN, and a
figure of crops and error maps where our error is largest. Temporal flicker on the animated
scene and on a static sequence of every still one: the frame-to-frame change of the residual
(denoised − reference), ours over each frame's temporal window against OIDN frame by frame.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench.common import OidnDenoise, image_metrics, true_error_map
from bench.dev_references import DevScene
from bench.quality_measures import mean_abs_change, shadow_contrast_ratio
from bench.report_images import save_figure
from models.pretrained import Networks
from service.images import linear_to_srgb
from service.loop.denoise_session import DenoiseSession
from service.loop.loop import RenderLoop
from service.loop.spec import LoopSpec
from service.loop.tensors import to_image
from service.render.framebuffer import FrameBuffer

try:  # optional: a dev dependency; the report notes when the figures are missing
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
except ImportError:
    plt = None

REPORT_NAME = "suite-quality.md"
SPP_LEVELS = (16, 64, 256)
METHODS = ("noisy", "kpcn", "oidn")
FLICKER_METHODS = METHODS + ("oidn_pooled",)  # + OIDN on the input our network filtered (sequence_images)
CROP = 64
ENERGY_TOLERANCE = 0.02  # the goal: mean radiance within 2 % of the reference on every scene (no lost energy)
SEED = 1
STATIC_FRAMES = 4  # frames of the static sequence a still scene is rendered as, for its flicker
# Regions (top, bottom, left, right as frame fractions) of one albedo crossed by hard shadows,
# where the shadow contrast is measured: hard_shadows' right wall with the lattice's shadow.
SHADOW_REGIONS = {"hard_shadows": (0.34, 0.73, 0.65, 0.91)}


@dataclass(frozen=True)
class Scores:
    smape: float
    relmse: float
    psnr: float
    energy: float  # mean radiance / the reference's


@dataclass
class SceneQuality:
    name: str
    scores: dict[int, dict[str, Scores]]  # spp → method → scores
    figure: Path | None = None
    shadow_contrast: dict[int, dict[str, float]] | None = None  # spp → method → share of the reference's


def score(image: np.ndarray, reference: np.ndarray) -> Scores:
    metrics = image_metrics(image, reference)
    energy = float(np.nan_to_num(image).mean() / max(float(reference.mean()), 1e-12))
    return Scores(metrics["smape"], metrics["relmse"], metrics["psnr"], energy)


def uniform_render(scene: DevScene, spp: int, networks: Networks, frames: int = 1, seed: int = SEED):
    spec = LoopSpec(scene=str(scene.path), frames=frames, spp_first=spp, max_iterations=1, allocator="uniform",
                    seed=seed)
    return next(iter(RenderLoop(spec, networks).run()))


def three_images(record, frame: int, oidn: OidnDenoise) -> dict[str, np.ndarray]:
    buffer = record.buffers[frame]
    return {"noisy": buffer.mean, "kpcn": record.denoised[frame], "oidn": oidn(buffer.mean, buffer.albedo, buffer.normal)}


def render_levels(scene: DevScene, networks: Networks, oidn: OidnDenoise,
                  spp_levels: tuple[int, ...] = SPP_LEVELS) -> dict[int, dict[str, np.ndarray]]:
    """spp → noisy / ours / OIDN images of one uniform render (seed SEED) per level."""
    return {spp: three_images(uniform_render(scene, spp, networks), 0, oidn) for spp in spp_levels}


def score_scene(scene: DevScene, reference: np.ndarray, shown: dict[int, dict[str, np.ndarray]],
                figures: Path | None) -> SceneQuality:
    """Scores (and the hard-shadow contrast, the crops figure) of `render_levels`' images."""
    scores, contrast = {}, {}
    region = SHADOW_REGIONS.get(scene.name)
    for spp, images in shown.items():
        scores[spp] = {method: score(image, reference) for method, image in images.items()}
        if region is not None:
            contrast[spp] = {method: shadow_contrast_ratio(image, reference, region) for method, image in images.items()}
    quality = SceneQuality(scene.name, scores, shadow_contrast=contrast or None)
    if figures is not None and plt is not None:
        quality.figure = write_crops(scene.name, shown, reference, figures)
    return quality


def sequence_images(buffers: list[FrameBuffer], networks: Networks, oidn: OidnDenoise) -> list[dict[str, np.ndarray]]:
    """Per frame of a sequence: the noisy mean, ours over its temporal window (as the loop runs a
    multi-frame job: DenoiseSession, the shipped network's radius), OIDN on the frame alone, and
    OIDN on the very input our network filtered (for a single-frame network, the window's pooled
    samples, models.accumulation) — which separates what the window adds from what the network does."""
    session = DenoiseSession(networks, len(buffers), networks.denoiser.config.temporal_radius)
    ours = session.denoise(buffers, np.ones(buffers[0].shape, np.float32))
    images = []
    for f, buffer in enumerate(buffers):
        pooled = session.inputs[f]
        images.append({"noisy": buffer.mean, "kpcn": to_image(ours[f]),
                       "oidn": oidn(buffer.mean, buffer.albedo, buffer.normal),
                       "oidn_pooled": oidn(to_image(pooled.color), buffer.albedo, buffer.normal)})
    return images


def temporal_flicker(scene: DevScene, references: list[np.ndarray], networks: Networks, oidn: OidnDenoise,
                     spp: int = SPP_LEVELS[0]) -> dict[str, float]:
    """Mean |Δ residual| between consecutive frames, linear radiance: 0 = the error does not
    change from frame to frame, whatever the scene's own motion. One reference per frame; a
    still scene given copies of its one reference is a static sequence (every frame its own
    seed). Also each method's mean SMAPE over the sequence (key `smape_<method>`): steadier
    must not mean worse."""
    return sequence_flicker(render_sequence(scene, len(references), networks, spp), references, networks, oidn)


def render_sequence(scene: DevScene, frames: int, networks: Networks, spp: int = SPP_LEVELS[0]) -> list[FrameBuffer]:
    """The sequence temporal_flicker scores: the scene's frames, or a still scene's one frame
    rendered `frames` times with seeds SEED + f. One uniform iteration: the samples do not
    depend on the networks, so one render serves every network scored on it."""
    if scene.frames > 1:
        return uniform_render(scene, spp, networks, frames=frames).buffers
    # the service refuses frames > 1 without $frame: one render per seed, one sequence
    return [uniform_render(scene, spp, networks, seed=SEED + f).buffers[0] for f in range(frames)]


def sequence_flicker(buffers: list[FrameBuffer], references: list[np.ndarray], networks: Networks,
                     oidn: OidnDenoise) -> dict[str, float]:
    """temporal_flicker's scores of a rendered sequence (render_sequence) denoised by `networks`."""
    per_frame = sequence_images(buffers, networks, oidn)
    out = {}
    for method in FLICKER_METHODS:
        residuals = [np.nan_to_num(images[method]) - ref for images, ref in zip(per_frame, references)]
        out[method] = mean_abs_change(residuals)
        out[f"smape_{method}"] = float(np.mean([image_metrics(images[method], ref)["smape"]
                                                for images, ref in zip(per_frame, references)]))
    return out


def _hardest_crop(error: np.ndarray) -> tuple[slice, slice]:
    """The CROP² window with the largest summed error (integral image)."""
    h, w = error.shape
    size_y, size_x = min(CROP, h), min(CROP, w)
    integral = np.pad(error, ((1, 0), (1, 0))).cumsum(0).cumsum(1)
    sums = (integral[size_y:, size_x:] - integral[:-size_y, size_x:] - integral[size_y:, :-size_x]
            + integral[:-size_y, :-size_x])
    y, x = np.unravel_index(int(np.argmax(sums)), sums.shape)
    return slice(y, y + size_y), slice(x, x + size_x)


def write_crops(name: str, shown: dict[int, dict[str, np.ndarray]], reference: np.ndarray, folder: Path) -> Path:
    """Rows: each spp level; columns: noisy, KPCN, OIDN, reference, KPCN error, OIDN error —
    all on the crop where KPCN's 16-spp error is largest."""
    folder.mkdir(parents=True, exist_ok=True)
    levels = sorted(shown)
    rows, cols = _hardest_crop(true_error_map(shown[levels[0]]["kpcn"], reference))
    fig, axes = plt.subplots(len(levels), 6, figsize=(9.0, 1.6 * len(levels)), squeeze=False)
    for row, spp in zip(axes, levels):
        images = shown[spp]
        errors = {m: true_error_map(images[m], reference)[rows, cols] for m in ("kpcn", "oidn")}
        top = max(float(e.max()) for e in errors.values()) or 1.0
        panels = [(linear_to_srgb(images[m][rows, cols]), f"{spp} spp {m}", None) for m in METHODS]
        panels += [(linear_to_srgb(reference[rows, cols]), "reference", None)]
        panels += [(errors[m], f"{m} SMAPE map", top) for m in ("kpcn", "oidn")]
        for ax, (image, title, vmax) in zip(row, panels):
            ax.imshow(image, vmin=0 if vmax else None, vmax=vmax, cmap="magma" if vmax else None,
                      interpolation="nearest")
            ax.set_title(title, fontsize=6)
            ax.axis("off")
    fig.suptitle(f"{name}: the {CROP}² crop where KPCN's 16-spp error is largest", fontsize=7)
    path = folder / f"{name}.png"
    save_figure(fig, path, dpi=80, bbox_inches="tight")  # rewritten only when the picture changed
    plt.close(fig)
    return path
