"""The built-in scenes: each is a named `(frame) -> dict` for `mi.load_dict`, with a one-line blurb.

The registry is an explicit tuple (not a string-keyed factory), so an unknown name fails at
lookup time with the list of known ones, and `renderloop render --list` reads the same table.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from service.render.builtin.cornell import cornell_box, cornell_box_orbit
from service.render.builtin.fireflies import fireflies
from service.render.builtin.glossy_spheres import glossy_spheres
from service.render.builtin.veiled import veiled


@dataclass(frozen=True)
class BuiltinScene:
    name: str
    description: str
    build: Callable[[int], dict]


BUILTIN_SCENES: tuple[BuiltinScene, ...] = (
    BuiltinScene("cornell-box", "Mitsuba's Cornell box: diffuse walls, two blocks, one area light", cornell_box),
    BuiltinScene(
        "cornell-box-orbit",
        "Cornell box with the camera swinging along a small arc each frame (a sequence: with frames > 1 it "
        "gets motion vectors and temporal denoising)",
        cornell_box_orbit,
    ),
    BuiltinScene(
        "glossy-spheres",
        "Cornell room with a rough gold sphere, a rough blue plastic sphere and a smooth glass sphere",
        glossy_spheres,
    ),
    BuiltinScene(
        "fireflies",
        "Cornell room lit mostly indirectly by a tiny, very bright shaded sphere light (firefly-prone)",
        fireflies,
    ),
    BuiltinScene(
        "veiled",
        "Cornell box whose tall block is a cube of homogeneous scattering fog (needs volpath)",
        veiled,
    ),
)

BUILTIN_BY_NAME: dict[str, BuiltinScene] = {scene.name: scene for scene in BUILTIN_SCENES}
