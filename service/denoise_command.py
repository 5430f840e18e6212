"""`renderloop denoise IN.exr [--lambda L | --lambda-map MAP.exr] [--frames …] -o OUT.exr`:
arguments → service.exr_denoise.denoise_exr."""
from __future__ import annotations

from pathlib import Path

from service.loop.spec import LAMBDA_RANGE, LoopSpec, lambda_problem


def add_parser(sub) -> None:
    p = sub.add_parser("denoise", help="denoise an EXR in the renderloop layout or an aov render of Mitsuba's")
    p.add_argument("input", type=Path, help="EXR with noisy.*, variance.*, albedo.*, N.*, Z layers (renderloop render "
                   "--no-denoise), or Mitsuba's: R,G,B with albedo.*, sh_normal.* or nn.*, and optionally Z.T or dd.T")
    p.add_argument("--spp", type=int, help="samples per pixel of an input without an spp layer (e.g. the scene's "
                   "sample_count for mi.render's EXR); the error layer needs it")
    lam = p.add_mutually_exclusive_group()
    default_lam = LoopSpec(scene="").lam
    lam.add_argument("--lambda", dest="lam", type=float, default=default_lam,
                     help=f"global λ in [{LAMBDA_RANGE[0]:g}, {LAMBDA_RANGE[1]:g}] (default {default_lam:g})")
    lam.add_argument("--lambda-map", type=Path, help="single-channel EXR (layer `lambda` or R) of per-pixel λ")
    p.add_argument("--frames", type=Path, nargs="+", default=[],
                   help="neighbour frames in sequence order, the input among them or not (temporal window)")
    p.add_argument("-o", "--output", type=Path, required=True, help="output EXR path")
    p.add_argument("--png", action="store_true", help="also write a tonemapped PNG beside the EXR")
    p.add_argument("--weights", type=Path, help="folder holding denoiser.pt and error_predictor.pt "
                   "(default: $RENDERLOOP_WEIGHTS_DIR, else the shipped weights)")
    p.set_defaults(handler=run_denoise)


def run_denoise(args) -> int:
    # torch, OpenEXR and the networks: imported only when the command runs (`--help` stays fast)
    from models.pretrained import load_networks
    from service.exr import ExrError, require_exr_path
    from service.exr_denoise import NO_VARIANCE_NOTE, denoise_exr
    from service.images import tonemap, write_png
    from service.loop.tensors import configure_torch_threads
    from service.render.runtime import network_device

    require_exr_path(args.output)
    if args.lambda_map is None and lambda_problem(args.lam):  # fail before the weights load
        raise ExrError(f"--lambda: {lambda_problem(args.lam)} (got {args.lam})")
    if args.spp is not None and args.spp < 1:
        raise ExrError(f"--spp must be >= 1 (got {args.spp})")
    configure_torch_threads()
    networks = load_networks(args.weights, device=network_device())
    frame = denoise_exr(args.input, args.output, networks, lam=args.lam, lambda_map=args.lambda_map, frames=args.frames,
                        spp=args.spp)
    if frame.variance is None:
        print(f"note: {NO_VARIANCE_NOTE}")
    if frame.error is not None:
        estimate = f"mean predicted SMAPE {frame.error.mean():.4f}"
    elif frame.variance is None:
        estimate = "no error estimate: no variance layer"
    else:
        estimate = "no error estimate: the input has no spp layer, which the error network reads (give --spp N)"
    print(f"wrote {args.output}  ({estimate})")
    if args.png:
        print(f"wrote {write_png(args.output.with_suffix('.png'), tonemap(frame.color))}")
    return 0
