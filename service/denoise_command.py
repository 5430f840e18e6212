"""`renderloop denoise IN.exr [--lambda L | --lambda-map MAP.exr] [--frames …] -o OUT.exr`.

Denoises a file in the project's EXR layout (as written by `renderloop render --no-denoise`)
and writes `R,G,B` (denoised) and `error` (predicted SMAPE) beside the input layers.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from models.frames import FrameTensors
from models.pretrained import load_networks
from service.exr import ExrError, ExrFrame, read_exr, write_exr
from service.loop.spec import LAMBDA_RANGE, lambda_problem
from service.loop.tensors import configure_torch_threads, lam_tensor, nchw, to_image

REQUIRED_LAYERS = ("noisy", "variance", "albedo", "normal", "depth")


def add_parser(sub) -> None:
    p = sub.add_parser("denoise", help="denoise an EXR in the renderloop layout")
    p.add_argument("input", type=Path, help="EXR with noisy.*, variance.*, albedo.*, N.*, Z layers")
    lam = p.add_mutually_exclusive_group()
    lam.add_argument("--lambda", dest="lam", type=float, default=1.0,
                     help=f"global λ in [{LAMBDA_RANGE[0]:g}, {LAMBDA_RANGE[1]:g}] (default 1)")
    lam.add_argument("--lambda-map", type=Path, help="single-channel EXR (layer `lambda` or R) of per-pixel λ")
    p.add_argument("--frames", type=Path, nargs="+", default=[],
                   help="neighbour frames in sequence order, the input among them or not (temporal window)")
    p.add_argument("-o", "--output", type=Path, required=True)
    p.add_argument("--weights", type=Path, help="folder holding denoiser.pt and error_predictor.pt "
                   "(default: $RENDERLOOP_WEIGHTS_DIR, else the shipped weights)")
    p.set_defaults(handler=run_denoise)


def frame_from_exr(path: Path, frame: ExrFrame):
    """ExrFrame → models.frames.FrameTensors (1, C, H, W)."""
    missing = [name for name in REQUIRED_LAYERS if getattr(frame, name) is None]
    if missing:
        raise ExrError(f"{path}: missing layers {', '.join(missing)} (render with --no-denoise to get them)")

    return FrameTensors(color=nchw(frame.noisy), variance=nchw(frame.variance), albedo=nchw(frame.albedo),
                        normal=nchw(frame.normal), depth=nchw(frame.depth),
                        motion=None if frame.motion is None else nchw(frame.motion))


def load_lambda(args, shape: tuple[int, int]) -> np.ndarray:
    if args.lambda_map is None:
        if lambda_problem(args.lam):
            raise ExrError(f"--lambda: {lambda_problem(args.lam)} (got {args.lam})")
        return np.full(shape, args.lam, dtype=np.float32)
    m = read_exr(args.lambda_map)
    lam = m.lam if m.lam is not None else (m.color[..., 0] if m.color is not None else None)
    if lam is None:
        raise ExrError(f"{args.lambda_map}: no `lambda` or R layer")
    if lam.shape != shape:
        raise ExrError(f"{args.lambda_map}: λ map is {lam.shape[1]}x{lam.shape[0]}, the image is {shape[1]}x{shape[0]}")
    if lambda_problem(lam):
        raise ExrError(f"{args.lambda_map}: {lambda_problem(lam)}")
    return lam.astype(np.float32)


def run_denoise(args) -> int:
    centre_frame = read_exr(args.input)
    paths = [Path(p) for p in args.frames]
    if paths and args.input.resolve() not in [p.resolve() for p in paths]:
        raise ExrError("--frames must include the input file so its position in the sequence is known")
    paths = paths or [args.input]
    frames = [centre_frame if p.resolve() == args.input.resolve() else read_exr(p) for p in paths]
    for p, f in zip(paths, frames):
        if f.shape != centre_frame.shape:
            raise ExrError(f"{p}: size {f.shape[::-1]} differs from the input's {centre_frame.shape[::-1]}")
    centre = [p.resolve() for p in paths].index(args.input.resolve())
    window = [frame_from_exr(p, f) for p, f in zip(paths, frames)]
    lam = load_lambda(args, centre_frame.shape)

    configure_torch_threads()
    networks = load_networks(args.weights)
    denoiser, error_predictor = networks.denoiser, networks.error_predictor
    with torch.no_grad():
        denoised = denoiser(window, centre, lam_tensor(lam))
        error = error_predictor(window[centre], denoised)
    centre_frame.color = to_image(denoised)
    centre_frame.error = to_image(error)
    centre_frame.lam = lam
    print(f"wrote {write_exr(args.output, centre_frame)}  (mean predicted SMAPE {centre_frame.error.mean():.4f})")
    return 0
