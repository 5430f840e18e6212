"""Denoise a file in the project's EXR layout (as written by `renderloop render --no-denoise`):
`R,G,B` (denoised) and `error` (predicted SMAPE) are written beside the input layers."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from models.error_predictor import reads_disagreement
from models.frames import FrameTensors
from models.kernel_disagreement import apply_for_error_network
from models.pretrained import Networks
from service.exr import ExrError, ExrFrame, read_exr, write_exr
from service.loop.oidn import candidate_for
from service.loop.spec import lambda_problem
from service.loop.tensors import lam_tensor, nchw, to_image

REQUIRED_LAYERS = ("noisy", "variance", "albedo", "normal", "depth")
# EXR layer names of each required field, for the message (service/exr.py owns the layout).
LAYER_NAMES = {"noisy": "noisy.R/G/B", "variance": "variance.R/G/B", "albedo": "albedo.R/G/B",
               "normal": "N.X/Y/Z", "depth": "Z"}


def frame_from_exr(path: Path, frame: ExrFrame) -> FrameTensors:
    """ExrFrame → models.frames.FrameTensors (1, C, H, W)."""
    missing = [name for name in REQUIRED_LAYERS if getattr(frame, name) is None]
    if missing:
        # An EXR from mi.render (even with the aov integrator's albedo/normal) has no per-pixel
        # variance of the mean, which the denoiser's features need: say so and how to get one.
        raise ExrError(f"{path}: missing layers {', '.join(LAYER_NAMES[m] for m in missing)}; an EXR written by "
                       f"mi.render lacks at least the variance of the mean — render the scene with "
                       f"`renderloop render SCENE --no-denoise -o x.exr` to get every layer")
    return FrameTensors(color=nchw(frame.noisy), variance=nchw(frame.variance), albedo=nchw(frame.albedo),
                        normal=nchw(frame.normal), depth=nchw(frame.depth),
                        motion=None if frame.motion is None else nchw(frame.motion),
                        spp=None if frame.spp is None else nchw(frame.spp.astype(np.float32)))


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
                frames: list[Path] | None = None) -> ExrFrame:
    """Denoise `source` (with its temporal neighbours `frames`, the source among them) and
    write the result to `output`; returns the written frame."""
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
    window = [frame_from_exr(p, f) for p, f in zip(paths, loaded)]
    lam_map = load_lambda(lam, lambda_map, centre_frame.shape)
    with torch.no_grad():
        window, centre = networks.denoiser.filtered_window(window, centre)  # a single-frame network pools it
        filtered = window[centre]
        candidate = candidate_for(networks.denoiser, filtered)
        with_disagreement = reads_disagreement(networks.error_predictor)
        denoised, disagreement = apply_for_error_network(networks.denoiser,
                                                         networks.denoiser.prepare(window, centre, candidate),
                                                         candidate, lam_tensor(lam_map), with_disagreement)
        # An error network that reads sample counts needs the EXR's `spp` layer; without one the
        # file still gets its denoised image, only no error estimate.
        wants_spp = networks.error_predictor.config.sample_count_input
        error = None if (wants_spp and filtered.spp is None) else networks.error_predictor(filtered, denoised,
                                                                                            disagreement)
    centre_frame.color = to_image(denoised)
    centre_frame.error = None if error is None else to_image(error)
    centre_frame.lam = lam_map
    write_exr(output, centre_frame)
    return centre_frame
