"""Which of a stratifying sampler's dimensions buy `mi.render` its variance? (docs/fidelity.md,
"The scene's sampler")

Renders a scenes/dev scene in one uniform pass over several seeds three ways and prints the
per-pixel relative variance of the raw (splatted) image and of the per-pixel estimates:
`independent` everywhere; film and lens stratified (service/render/stratified_sequence.py, what
the renderer does); and film and lens stratified with Mitsuba's own sampler of the scene's kind
also driving the integrator's dimensions — possible here only because the pass is uniform and
its lanes are laid out pixel-major, as `mi.render` lays them out (`set_samples_per_wavefront`).
Then `mi.render` itself with `independent` and with the scene's sampler.

    python -m bench.experiments.sampler_dimensions fine_texture [--spp 16] [--seeds 6]

At the scene's own film size, both renderers.
"""
from __future__ import annotations

import argparse
import re
import tempfile
from pathlib import Path

import numpy as np

import service.render.renderer as renderer
from service.render.framebuffer import FrameBuffer
from service.render.runtime import mitsuba
from service.render.scenes import load_scene_info

SCENES = Path(__file__).resolve().parents[2] / "scenes" / "dev"
# relMSE's ε: keeps dark pixels from dominating the relative variance.
EPS = 1e-2


def relative_variance(images: list[np.ndarray]) -> float:
    """Mean over pixels of the variance across seeds over the squared mean."""
    stack = np.array(images)
    mean = stack.mean(axis=0)
    return float((stack.var(axis=0, ddof=1) / (mean ** 2 + EPS)).mean())


class _MitsubaWithSampler:
    """`mitsuba()` whose independent sampler is replaced by one of `kind` with `spp` samples per
    pixel, so the integrator's dimensions are stratified too (uniform passes only)."""

    def __init__(self, mi, kind: str, spp: int):
        self.mi, self.kind, self.spp = mi, kind, spp

    def __getattr__(self, name):
        return getattr(self.mi, name)

    def load_dict(self, description):
        if description != {"type": "independent"}:
            return self.mi.load_dict(description)
        sampler = self.mi.load_dict({"type": self.kind, "sample_count": self.spp})
        sampler.set_samples_per_wavefront(self.spp)
        return sampler


def ours(scene, spp: int, seeds: int) -> tuple[float, float]:
    width, height = scene.sensors()[0].film().crop_size()
    raw, estimates = [], []
    for seed in range(seeds):
        buffer = FrameBuffer.empty(height, width)
        renderer.render_samples(scene, np.full((height, width), spp), buffer, seed=seed)
        raw.append(buffer.raw.copy())
        estimates.append(buffer.radiance_sum / buffer.spp[..., None])
    return relative_variance(raw), relative_variance(estimates)


def mitsuba_variance(name: str, kind: str, spp: int, seeds: int) -> float:
    """mi.render of the scene file with its sampler replaced by `kind`."""
    mi = mitsuba()
    source = (SCENES / name / "scene.xml").read_text()
    edited = re.sub(r'sampler type="[a-z]+"', f'sampler type="{kind}"', source)
    # Written beside the original so its relative asset paths resolve.
    with tempfile.NamedTemporaryFile("w", suffix=".xml", dir=SCENES / name) as file:
        file.write(edited)
        file.flush()
        scene = mi.load_file(file.name, spp=str(spp))
    images = [np.asarray(mi.render(scene, spp=spp, seed=seed))[..., :3] for seed in range(seeds)]
    return relative_variance(images)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene")
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--seeds", type=int, default=6)
    args = parser.parse_args()
    scene = load_scene_info(SCENES / args.scene / "scene.xml").scene
    kind = re.search(r'sampler type="([a-z]+)"', (SCENES / args.scene / "scene.xml").read_text()).group(1)
    stratifying, real_mitsuba = renderer.is_stratifying, renderer.mitsuba
    rows = {}
    try:
        renderer.is_stratifying = lambda _sampler: False
        rows["independent"] = ours(scene, args.spp, args.seeds)
        renderer.is_stratifying = stratifying
        rows["film + lens stratified"] = ours(scene, args.spp, args.seeds)
        renderer.mitsuba = lambda: _MitsubaWithSampler(real_mitsuba(), kind, args.spp)
        rows[f"+ integrator's dimensions ({kind})"] = ours(scene, args.spp, args.seeds)
    finally:
        renderer.is_stratifying, renderer.mitsuba = stratifying, real_mitsuba
    for label, (raw, estimate) in rows.items():
        print(f"{args.scene} ours, {label}: relative variance raw {raw:.5f}, per-pixel estimate {estimate:.5f}")
    for kind_used in ("independent", kind):
        print(f"{args.scene} mi.render, {kind_used}: relative variance {mitsuba_variance(args.scene, kind_used, args.spp, args.seeds):.5f}")


if __name__ == "__main__":
    main()
