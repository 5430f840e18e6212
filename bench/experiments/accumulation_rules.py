"""Which neighbour pixels should a single-frame denoiser pool from its window? (models/accumulation.py;
docs/decisions.md, "`accumulate=False`, removed")

Chosen on validation material only, never the development suite:
- the eight validation scenes (scenes/val) as static sequences: FRAMES renders of the same view
  at SPP, each its own seed, against their committed references;
- the built-in `cornell-box-orbit` (the camera orbits: every pixel moves) and SPINNING_CUBE (a
  glossy textured cube turning under a fixed light: its shading slides over it) at SIZE²,
  FRAMES frames, against a REFERENCE_SPP render of each frame.

Per rule, every frame is pooled over its 3-frame window and denoised by the shipped network (one
frame, its OIDN candidate on the pooled input); printed: the mean SMAPE over the sequence and the
flicker (mean |Δ residual| between consecutive frames) of ours, and the share of neighbour pixels
pooled.

    python -m bench.experiments.accumulation_rules [--moving-only]
"""
from __future__ import annotations

import argparse
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from bench.common import image_metrics, load_bench_networks, pinned_torch_threads
from bench.dev_references import SUITES, dev_scenes, load_reference
from bench.quality_measures import mean_abs_change
from bench.suite_quality import SEED, uniform_render
from models.accumulation import (DEPTH_RELATIVE, aligned_to_center, consistent_pixels, pool, same_light,
                                 sample_counts)
from models.features import sanitize_frame
from models.frames import FrameTensors
from models.pretrained import Networks
from models.warp import flow_to_center
from service.loop.loop import RenderLoop
from service.loop.denoise_frame import denoise_frame
from service.loop.spec import LoopSpec
from service.loop.tensors import frame_tensors, to_image
from service.render.framebuffer import FrameBuffer

FRAMES = 5
SPP = 16
SIZE = 128
REFERENCE_SPP = 2048
Rule = Callable[[list[FrameTensors], int], tuple[FrameTensors, float]]


def still_pixels(window: list[FrameTensors], center: int, j: int) -> Tensor:
    """(N,1,H,W) bool: where frame j's pixel shows the center's without moving (|flow| ≤ 1e-3 px)."""
    flow, valid = flow_to_center([f.motion for f in window], center, j)
    if flow is None:
        return torch.ones_like(window[j].depth, dtype=torch.bool)
    return (flow.abs().amax(dim=1, keepdim=True) <= 1e-3) & (valid > 0.5)


def fixed_guides(center: FrameTensors, other: FrameTensors) -> Tensor:
    """The first rule's guide test: the same light test, fixed guide tolerances per pixel (no
    neighbourhood range)."""
    light = same_light(center, other)
    albedo = ((other.albedo - center.albedo).abs() <= 0.1).all(1, keepdim=True)
    normal = (other.normal - center.normal).norm(dim=1, keepdim=True) <= 0.25
    depth = (other.depth - center.depth).abs() <= DEPTH_RELATIVE * torch.maximum(other.depth, center.depth) + 1e-6
    return light & albedo & normal & depth


def rule(moved: bool, guides: Callable[[FrameTensors, FrameTensors], Tensor]) -> Rule:
    """moved: also pool pixels reprojected along the motion (bilinear); else still pixels only."""
    def pooled(window: list[FrameTensors], center: int) -> tuple[FrameTensors, float]:
        target, neighbours = window[center], []
        for j in range(len(window)):
            if j == center:
                continue
            if moved:
                other, valid = aligned_to_center(window, center, j)
            else:
                other, valid = window[j], still_pixels(window, center, j)
            neighbours.append((other, valid & guides(target, other)))
        share = float(np.mean([m.float().mean().item() for _, m in neighbours])) if neighbours else 0.0
        return pool(target, neighbours), share
    return pooled


def symmetric_moved(window: list[FrameTensors], center: int) -> tuple[FrameTensors, float]:
    """Still pixels from either side; a moved pixel only from both sides at once, with equal counts,
    so a change that is linear in time (shading sliding over a turning object) cancels to first order."""
    target, neighbours, masks = window[center], [], {}
    for j in range(len(window)):
        if j != center:
            other, valid = aligned_to_center(window, center, j)
            still = still_pixels(window, center, j)
            masks[j] = (other, valid & consistent_pixels(target, other), still)
    if len(masks) == 2:
        (prev, ok_p, still_p), (nxt, ok_n, still_n) = masks[center - 1], masks[center + 1]
        both = ok_p & ok_n & ~still_p & ~still_n
        counts = torch.minimum(sample_counts(prev), sample_counts(nxt))
        for other, ok, still in ((prev, ok_p, still_p), (nxt, ok_n, still_n)):
            factor = torch.where(still, ok.float(), both.float() * counts / sample_counts(other).clamp_min(1e-12))
            neighbours.append((other, factor))
    else:
        neighbours = [(o, ok & still) for o, ok, still in masks.values()]
    share = float(np.mean([(m > 0).float().mean().item() for _, m in neighbours]))
    return pool(target, neighbours), share


RULES: dict[str, Rule | None] = {
    "center alone": None,
    "still, 3×3-range guides": rule(False, consistent_pixels),
    "still, fixed guides": rule(False, fixed_guides),
    "moved too, 3×3-range guides (shipped)": rule(True, consistent_pixels),
    "moved too, fixed guides": rule(True, fixed_guides),
    "moved only from both sides": symmetric_moved,
}


def evaluate(buffers: list[FrameBuffer], references: list[np.ndarray], networks: Networks, name: str) -> None:
    frames = [sanitize_frame(frame_tensors(b))[0] for b in buffers]
    denoiser = networks.denoiser
    for label, chosen in RULES.items():
        images, share = [], []
        for f in range(len(frames)):
            lo, hi = max(0, f - 1), min(len(frames), f + 2)
            pooled, s = chosen(frames[lo:hi], f - lo) if chosen else (frames[f], 0.0)
            share.append(s)
            images.append(to_image(denoise_frame(denoiser, [pooled], 0)))
        smape = np.mean([image_metrics(i, r)["smape"] for i, r in zip(images, references)])
        flicker = mean_abs_change([np.nan_to_num(i) - r for i, r in zip(images, references)])
        print(f"| {name} | {label} | {smape:.4f} | {flicker:.5f} | {np.mean(share):.2f} |", flush=True)


# An object turning under a fixed light, fixed camera: the shading slides over its surface from
# frame to frame, which the motion vectors (the surface's motion) do not describe. Glossy and
# textured; 5 degrees per frame, built from $frame alone (Mitsuba XML has no arithmetic).
SPINNING_CUBE = """<scene version="3.0.0">
  <default name="frame" value="0"/>
  <integrator type="path"><integer name="max_depth" value="6"/></integrator>
  <sensor type="perspective"><float name="fov" value="40"/>
    <transform name="to_world"><lookat origin="0, 1.4, 3.2" target="0, 0.5, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="%d"/><integer name="height" value="%d"/></film></sensor>
  <shape type="cube"><transform name="to_world"><scale value="0.45"/>
      <rotate y="1" angle="$frame"/><rotate y="1" angle="$frame"/><rotate y="1" angle="$frame"/>
      <rotate y="1" angle="$frame"/><rotate y="1" angle="$frame"/><translate y="0.55"/></transform>
    <bsdf type="roughplastic"><float name="alpha" value="0.1"/>
      <texture type="checkerboard" name="diffuse_reflectance"><rgb name="color0" value="0.05, 0.2, 0.5"/>
        <rgb name="color1" value="0.6, 0.5, 0.3"/><transform name="to_uv"><scale value="4"/></transform></texture>
    </bsdf></shape>
  <shape type="sphere"><point name="center" x="0.9" y="0.3" z="0.3"/><float name="radius" value="0.3"/>
    <bsdf type="roughconductor"><string name="material" value="Au"/><float name="alpha" value="0.15"/></bsdf></shape>
  <shape type="rectangle"><transform name="to_world"><scale value="5"/><rotate x="1" angle="-90"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.5"/></bsdf></shape>
  <shape type="rectangle"><transform name="to_world"><scale x="0.5" y="0.3"/>
      <lookat origin="1.6, 2.6, 1.4" target="0, 0.5, 0" up="0, 1, 0"/></transform>
    <emitter type="area"><rgb name="radiance" value="15"/></emitter></shape>
  <emitter type="constant"><rgb name="radiance" value="0.1"/></emitter>
</scene>""" % (SIZE, SIZE)


def sequence(scene: str, spp: int, seed: int) -> list[FrameBuffer]:
    spec = LoopSpec(scene=scene, width=SIZE, height=SIZE, frames=FRAMES, spp_first=spp,
                    max_iterations=1, allocator="uniform", denoise=False, seed=seed)
    return next(iter(RenderLoop(spec, None).run())).buffers


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--moving-only", action="store_true", help="skip the validation scenes' static sequences")
    args = parser.parse_args()
    nets = load_bench_networks(None).networks
    print("| sequence | rule | SMAPE (mean over frames) | flicker | neighbour pixels pooled |\n|---|---|---:|---:|---:|")
    with pinned_torch_threads(2), torch.no_grad():
        with tempfile.TemporaryDirectory() as folder:
            cube = Path(folder) / "spinning_cube.xml"
            cube.write_text(SPINNING_CUBE)
            for scene, label in (("cornell-box-orbit", "cornell-box-orbit"), (str(cube), "spinning cube")):
                references = [b.mean for b in sequence(scene, REFERENCE_SPP, 99)]
                evaluate(sequence(scene, SPP, SEED), references, nets, f"{label} {SIZE}², {FRAMES} frames")
        for scene in [] if args.moving_only else dev_scenes(None, SUITES["val"].root):
            reference, _ = load_reference(SUITES["val"].references, scene, None)
            buffers = [uniform_render(scene, SPP, nets, seed=SEED + f).buffers[0] for f in range(FRAMES)]
            evaluate(buffers, [reference] * FRAMES, nets, f"{scene.name} (static)")


if __name__ == "__main__":
    main()
