"""The job options `renderloop render` and `renderloop submit` share, generated from the one job
spec (service/loop/spec.py): same flags, help and defaults for a local render and a server job.

`add_job_options` declares them on a sub-parser; `spec_from_args` turns parsed arguments back
into a LoopSpec. Every LoopSpec field a user may set has exactly one option here (JOB_FIELDS
says which flag sets it); tests/test_job_options.py fails when a new field has none.
"""
from __future__ import annotations

import argparse
from dataclasses import fields, replace

from service.loop.spec import (ALLOCATORS, DEFAULT_ITERATIONS, LAMBDA_RANGE, MAX_NAME_CHARS, PRIORITY_RANGE, LoopSpec,
                               LoopSpecError, default_allocator, validate_spec)

# LoopSpec field → the flag that sets it (fields set by the service alone are absent).
JOB_FIELDS = {
    "width": "--width", "height": "--height", "frames": "--frames", "spp_first": "--spp-first",
    "max_iterations": "--iterations", "spp_budget": "--spp-budget", "time_limit": "--time-limit",
    "target_error": "--target-error", "allocator": "--allocator", "denoise": "--no-denoise", "lam": "--lambda",
    "seed": "--seed", "params": "--param", "priority": "--priority", "name": "--name",
}
SERVICE_ONLY_FIELDS = ("priority", "name")  # a local render has no queue and no listing
SERVER_SET_FIELDS = ("scene", "budget_source")  # the positional SCENE; the budget's origin


class JobOptionError(ValueError):
    """A job option out of range; the message names the flag."""


def add_job_options(p: argparse.ArgumentParser, *, service: bool) -> None:
    """The job's options, defaults from LoopSpec. `service`: also the queue's (--priority, --name)."""
    d = LoopSpec(scene="")
    p.add_argument("--width", type=int, help="image width in pixels (with --height; default: the scene's film)")
    p.add_argument("--height", type=int, help="image height in pixels (with --width; default: the scene's film)")
    p.add_argument("--frames", type=int, default=d.frames,
                   help=f"frames of the scene's animation; the scene must use $frame (default {d.frames})")
    p.add_argument("--spp", type=int, help="one uniform pass of N samples per pixel, no adaptive iterations")
    p.add_argument("--spp-first", type=int, default=d.spp_first,
                   help=f"samples per pixel of iteration 0 (default {d.spp_first})")
    stop = p.add_argument_group("stopping rules (whichever comes first; default: the scene's <sampler> sample_count "
                                f"as --spp-budget, else --iterations {DEFAULT_ITERATIONS})")
    stop.add_argument("--iterations", type=int, help="maximum iterations")
    stop.add_argument("--spp-budget", type=float, help="mean samples per pixel, all iterations together")
    stop.add_argument("--time-limit", type=float, help="seconds")
    stop.add_argument("--target-error", type=float, help="stop when the mean predicted SMAPE is at most this")
    p.add_argument("--allocator", help=" | ".join(ALLOCATORS) + f": where new samples go (default "
                   f"{default_allocator(True)}; {default_allocator(False)} with --no-denoise)")
    p.add_argument("--no-denoise", action="store_true", help="write the plain Monte Carlo estimate")
    p.add_argument("--lambda", dest="lam", type=float, default=d.lam,
                   help=f"λ in [{LAMBDA_RANGE[0]:g}, {LAMBDA_RANGE[1]:g}] (default {d.lam:g})")
    p.add_argument("--seed", type=int, default=d.seed, help=f"random seed of the samples (default {d.seed})")
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   help="set the scene's $NAME parameter, like Mitsuba's -D (repeatable)")
    p.add_argument("--png", action="store_true", help="also write a tonemapped PNG beside each EXR")
    if service:
        low, high = PRIORITY_RANGE
        p.add_argument("--priority", type=int, default=d.priority,
                       help=f"queue order in [{low}, {high}]: higher-priority queued jobs start first "
                            f"(default {d.priority})")
        p.add_argument("--name", help=f"what `renderloop jobs` and the page call the job (at most {MAX_NAME_CHARS} "
                                      "characters; default: the scene's folder or file name, or the built-in's name)")


def scene_params(pairs: list[str]) -> dict[str, str]:
    params = {}
    for pair in pairs:
        name, sep, value = pair.partition("=")
        if not sep or not name:
            raise JobOptionError(f"--param takes NAME=VALUE, got {pair!r}")
        params[name] = value
    return params


def gives_stopping_rule(args: argparse.Namespace) -> bool:
    return any(v is not None for v in (args.spp, args.iterations, args.spp_budget, args.time_limit, args.target_error))


def spec_from_args(args: argparse.Namespace, scene: str, *, default_iterations: int | None = DEFAULT_ITERATIONS
                   ) -> LoopSpec:
    """The LoopSpec the options ask for. With no stopping rule, `default_iterations` (a server
    decides for itself: pass None and send none)."""
    if args.spp is not None:
        if args.spp < 1:
            raise JobOptionError(f"--spp must be >= 1 (got {args.spp})")
        first, iterations = args.spp, 1
    else:
        if args.spp_first < 1:
            raise JobOptionError(f"--spp-first must be >= 1 (got {args.spp_first})")
        first = args.spp_first
        iterations = args.iterations if gives_stopping_rule(args) else default_iterations
    for name in ("width", "height"):
        value = getattr(args, name)
        if value is not None and value < 1:
            raise JobOptionError(f"--{name} must be >= 1 (got {value})")
    service = {name: getattr(args, name) for name in SERVICE_ONLY_FIELDS if hasattr(args, name)}
    return LoopSpec(
        scene=scene, width=args.width, height=args.height, frames=args.frames, spp_first=first,
        max_iterations=iterations, spp_budget=args.spp_budget, time_limit=args.time_limit,
        target_error=args.target_error, allocator=args.allocator, denoise=not args.no_denoise,
        lam=args.lam, seed=args.seed, params=scene_params(args.param), **service,
    )


def api_fields(spec: LoopSpec) -> dict:
    """The POST /jobs fields of a spec built with `default_iterations=None`: checked here first
    with the spec's own rules (so a bad option fails before any upload), unset ones left to the
    server (its default budget: the scene's sample_count, else DEFAULT_ITERATIONS)."""
    try:
        validate_spec(replace(spec, max_iterations=spec.max_iterations or DEFAULT_ITERATIONS))
    except LoopSpecError as exc:
        raise JobOptionError(str(exc)) from exc
    stored = spec.to_stored()
    for name in SERVER_SET_FIELDS:
        stored.pop(name, None)
    if not spec.params:
        stored.pop("params")
    return {name: value for name, value in stored.items() if value is not None}


def settable_fields() -> set[str]:
    """LoopSpec fields a user sets: every field but those the server sets."""
    return {f.name for f in fields(LoopSpec)} - set(SERVER_SET_FIELDS)
