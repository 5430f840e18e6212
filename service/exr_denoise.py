"""Denoise a file in the project's EXR layout (as written by `renderloop render --no-denoise`)
or one Mitsuba wrote itself (an `aov` integrator's output, read by service/exr.py under
Mitsuba's names): `R,G,B` (denoised) and `error` (predicted SMAPE) are written beside the input
layers.

Mitsuba's EXRs carry no variance of the mean and no sample counts. Without a variance layer the
denoiser gets one estimated from the image itself (estimate_variance: each pixel against its four
neighbours, which assumes uncorrelated pixel noise — a box-filtered film). Measured on the Cornell
box at 64², 16 spp, two seeds (our own EXRs, `python -m bench.experiments.mitsuba_exr_denoise`):
the denoised image is as good as with the true variance (SMAPE 0.0439 / 0.0426 vs 0.0439 /
0.0427), but the error network's mean predicted SMAPE read 0.62–0.63 for a true 0.043 (0.018
with the true variance), so no error layer is written on an estimate. Without depth the depth plane is zero; without an spp
layer the error network, which reads sample counts, needs `spp` given.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from models.frames import FrameTensors
from models.pretrained import Networks
from service.exr import ExrError, ExrFrame, read_exr, write_exr
from service.loop.denoise_frame import denoise_and_predict
from service.loop.spec import lambda_problem
from service.loop.tensors import lam_tensor, nchw, to_image

REQUIRED_LAYERS = ("albedo", "normal")
# EXR layer names of each required field, for the message (service/exr.py owns the layout).
LAYER_NAMES = {"albedo": "albedo.R/G/B", "normal": "N.X/Y/Z (Mitsuba: sh_normal.X/Y/Z or nn.X/Y/Z)"}
MITSUBA_RECIPE = ('render it with an aov integrator around yours: <integrator type="aov"><string name="aovs" '
                  'value="albedo:albedo,nn:sh_normal,dd:depth"/><integrator type="path" name="img"/></integrator>, '
                  'or use `renderloop render SCENE --no-denoise -o x.exr`')
# One line on what an input without a variance layer loses (printed by `renderloop denoise`).
NO_VARIANCE_NOTE = ("no variance layer: the denoiser used one estimated from the image itself (each pixel against its "
                    "neighbours; right for a box filter), so no error layer is written (on an estimate it reads ~15x "
                    "too high) and the λ tail trades noise for detail against that estimate, in which edges and "
                    "texture count as noise")
# Var(x − mean of its 4 neighbours) = σ²(1 + 1/4) for uncorrelated noise of equal σ.
NEIGHBOUR_RESIDUAL_GAIN = 1.25
NOISE_WINDOW = 7  # pixels on a side over which the squared residuals are averaged


def estimate_variance(radiance: np.ndarray) -> np.ndarray:
    """The variance of each pixel's mean, (H, W, 3), from the image alone: the squared residual
    against the mean of the four neighbours, averaged over NOISE_WINDOW² pixels. Edges and
    texture count as noise too (an overestimate there); spatially correlated noise (a tent or
    Gaussian film) partly cancels (an underestimate)."""
    padded = np.pad(radiance.astype(np.float64), ((1, 1), (1, 1), (0, 0)), mode="edge")
    neighbours = (padded[:-2, 1:-1] + padded[2:, 1:-1] + padded[1:-1, :-2] + padded[1:-1, 2:]) / 4.0
    squared = (radiance - neighbours) ** 2 / NEIGHBOUR_RESIDUAL_GAIN
    return box_mean_edge(squared, NOISE_WINDOW).astype(np.float32)


def box_mean_edge(x: np.ndarray, size: int) -> np.ndarray:
    """Mean over the size×size window (size odd) around each pixel of (H, W, C), the border
    pixels repeated outwards (scipy.ndimage.uniform_filter's mode "nearest", without scipy: the
    product does not depend on it): running sums along each axis, as a summed-area table."""
    r = size // 2
    padded = np.pad(x.astype(np.float64), ((r, r), (r, r), (0, 0)), mode="edge")
    for axis in (0, 1):
        sums = np.cumsum(padded, axis=axis)
        zero = np.zeros_like(np.take(sums, [0], axis=axis))
        sums = np.concatenate([zero, sums], axis=axis)
        n = sums.shape[axis]
        padded = np.take(sums, range(size, n), axis=axis) - np.take(sums, range(0, n - size), axis=axis)
    return padded / (size * size)


def frame_from_exr(path: Path, frame: ExrFrame, spp: int | None = None) -> FrameTensors:
    """ExrFrame → models.frames.FrameTensors (1, C, H, W); `spp` stands in for a missing spp layer."""
    radiance = frame.noisy if frame.noisy is not None else frame.color
    if radiance is None:
        raise ExrError(f"{path}: no radiance layer (noisy.R/G/B, R,G,B or <integrator name>.R/G/B)")
    missing = [name for name in REQUIRED_LAYERS if getattr(frame, name) is None]
    if missing:
        raise ExrError(f"{path}: missing layers {', '.join(LAYER_NAMES[m] for m in missing)}; {MITSUBA_RECIPE}")
    variance = frame.variance if frame.variance is not None else estimate_variance(radiance)
    depth = frame.depth if frame.depth is not None else np.zeros(radiance.shape[:2], np.float32)
    counts = frame.spp.astype(np.float32) if frame.spp is not None else (
        None if spp is None else np.full(radiance.shape[:2], spp, np.float32))
    return FrameTensors(color=nchw(radiance), variance=nchw(variance), albedo=nchw(np.clip(frame.albedo, 0.0, 1.0)),
                        normal=nchw(frame.normal), depth=nchw(depth),
                        motion=None if frame.motion is None else nchw(frame.motion),
                        spp=None if counts is None else nchw(counts))


def load_lambda(lam: float, lambda_map: Path | None, shape: tuple[int, int]) -> np.ndarray:
    """A global λ, or the per-pixel λ of a single-channel EXR (layer `lambda` or R)."""
    if lambda_map is None:
        if lambda_problem(lam):
            raise ExrError(f"--lambda: {lambda_problem(lam)} (got {lam})")
        return np.full(shape, lam, dtype=np.float32)
    m = read_exr(lambda_map)
    values = m.lam if m.lam is not None else (m.color[..., 0] if m.color is not None else None)
    if values is None:
        raise ExrError(f"{lambda_map}: no `lambda` or R layer")
    if values.shape != shape:
        raise ExrError(f"{lambda_map}: λ map is {values.shape[1]}x{values.shape[0]}, the image is {shape[1]}x{shape[0]}")
    if lambda_problem(values):
        raise ExrError(f"{lambda_map}: {lambda_problem(values)}")
    return values.astype(np.float32)


def denoise_exr(source: Path, output: Path, networks: Networks, *, lam: float = 1.0, lambda_map: Path | None = None,
                frames: list[Path] | None = None, spp: int | None = None) -> ExrFrame:
    """Denoise `source` (with its temporal neighbours `frames`, the source among them) and
    write the result to `output`; returns the written frame. `spp`: the samples per pixel of
    inputs without an spp layer (Mitsuba's sample_count)."""
    centre_frame = read_exr(source)
    paths = [Path(p) for p in frames or []]
    if paths and source.resolve() not in [p.resolve() for p in paths]:
        raise ExrError("--frames must include the input file so its position in the sequence is known")
    paths = paths or [source]
    loaded = [centre_frame if p.resolve() == source.resolve() else read_exr(p) for p in paths]
    for p, f in zip(paths, loaded):
        if f.shape != centre_frame.shape:
            raise ExrError(f"{p}: size {f.shape[::-1]} differs from the input's {centre_frame.shape[::-1]}")
    centre = [p.resolve() for p in paths].index(source.resolve())
    device = next(networks.denoiser.parameters()).device  # the GPU when the networks are there
    window = [frame_from_exr(p, f, spp).to(device) for p, f in zip(paths, loaded)]
    lam_map = load_lambda(lam, lambda_map, centre_frame.shape)
    with torch.no_grad():
        window, centre = networks.denoiser.filtered_window(window, centre)  # a single-frame network pools it
        filtered = window[centre]
        # The error network reads sample counts: without the EXR's `spp` layer (or --spp) the file
        # still gets its denoised image, only no error estimate. Nor is there one on an estimated
        # variance (see the module's docstring for the measurement).
        predictable = centre_frame.variance is not None and filtered.spp is not None
        result = denoise_and_predict(networks, window, centre, lam_tensor(lam_map), predict=predictable)
        denoised, error = result.image, result.error
    if centre_frame.noisy is None:  # Mitsuba's file: its radiance is the noisy input, kept beside the result
        centre_frame.noisy = centre_frame.color
    if centre_frame.spp is None and spp is not None:
        centre_frame.spp = np.full(centre_frame.shape, spp, np.uint32)
    centre_frame.color = to_image(denoised)
    centre_frame.error = None if error is None else to_image(error)
    centre_frame.lam = lam_map
    write_exr(output, centre_frame)
    return centre_frame
