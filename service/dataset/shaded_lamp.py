"""Rooms lit by one tiny, very bright bulb inside an opaque lampshade (issue 13's "a room lit by a
small very bright light (fireflies)").

Where both the training scenes and the denoiser fail together: light from a source a few
centimetres across reaches most surfaces only after a bounce, so a 16-spp render is a field of
fireflies — camera paths that happened to find the bulb — over dim, noisy walls. The procedural
rooms are lit by lights the camera paths find easily (a 20 % chance adds one unshaded tiny
sphere), and the validation scenes of this kind (scenes/val: shaded_bulb_study, misty_lantern)
and the suite's lamp_room are where the U-Net ensemble's kernels kept fireflies and the error
network ranked pixels no better than chance (docs/decisions.md: "The U-Net trunk, removed", "Rooms lit by a
tiny shaded bulb").

The room is closed on all four sides like the window layout's (the camera stays inside); a drum
shade — an open cylinder, opaque and two-sided, open at top and bottom — hangs or stands in it
with the bulb at its centre, so the bulb lights a disc of ceiling and a disc of floor directly
and everything else only through them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

Vec3 = tuple[float, float, float]
Color = tuple[float, float, float]

BULB_RADIUS = (0.01, 0.025)
SHADE_RADIUS = (0.12, 0.25)
SHADE_HALF_HEIGHT = (0.08, 0.16)
# Bulb strength: the direct irradiance of the floor disc under the shade is about this (times a
# log-normal exposure), E ≈ L·πr²/h² for a sphere of radiance L and radius r at height h; the
# room's walls then sit 1–2 orders of magnitude lower, the range of the scenes above.
FLOOR_IRRADIANCE = 4.0
WALL_MARGIN = 0.5


@dataclass(frozen=True)
class ShadeSpec:
    centre: Vec3          # the bulb's centre, also the shade's
    shade_radius: float
    shade_half_height: float
    bulb_radius: float
    radiance: Color       # the bulb's
    shade_color: Color    # the shade's diffuse reflectance (both sides)


def sample_shade(rng: np.random.Generator, room: Vec3, exposure: float, tint: Color) -> ShadeSpec:
    """A shade somewhere over the floor, between table and pendant height; `tint` (mean 1) the
    bulb's colour, `exposure` its brightness factor."""
    width, height, depth = room
    x = float(rng.uniform(-width / 2 + WALL_MARGIN, width / 2 - WALL_MARGIN))
    z = float(rng.uniform(-depth / 2 + WALL_MARGIN, depth / 2 - WALL_MARGIN))
    y = float(rng.uniform(0.8, height - 0.5))
    bulb = float(rng.uniform(*BULB_RADIUS))
    radiance = FLOOR_IRRADIANCE * exposure * y**2 / (math.pi * bulb**2)
    return ShadeSpec(centre=(x, y, z), shade_radius=float(rng.uniform(*SHADE_RADIUS)),
                     shade_half_height=float(rng.uniform(*SHADE_HALF_HEIGHT)), bulb_radius=bulb,
                     radiance=tuple(float(c * radiance) for c in tint),
                     shade_color=tuple(float(c) for c in rng.uniform(0.4, 0.85, 3)))


def shade_shapes(shade: ShadeSpec, index: int) -> dict[str, dict]:
    """The bulb (a sphere emitter) and its drum shade (an open cylinder, seen from both sides)."""
    x, y, z = shade.centre
    h = shade.shade_half_height
    return {
        f"light{index}_bulb": {"type": "sphere", "center": [x, y, z], "radius": shade.bulb_radius,
                               "emitter": {"type": "area", "radiance": {"type": "rgb", "value": list(shade.radiance)}}},
        f"light{index}_shade": {"type": "cylinder", "p0": [x, y - h, z], "p1": [x, y + h, z],
                                "radius": shade.shade_radius,
                                "bsdf": {"type": "twosided", "bsdf": {
                                    "type": "diffuse", "reflectance": {"type": "rgb", "value": list(shade.shade_color)}}}},
    }
