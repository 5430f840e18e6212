"""A room lit through a bounce off the ceiling by a tiny, very bright sphere light.

A shade just under the bulb keeps direct light off the floor and the lower walls, so the room
is lit by a small, intensely bright hot spot on the ceiling. Paths that reach that hot spot by
BSDF sampling from the floor are rare and carry huge weights: the classic firefly generator.
"""
from __future__ import annotations

from service.render.builtin.cornell import cornell_base
from service.render.runtime import mitsuba

BULB_POSITION = (0.0, 0.93, 0.0)
BULB_RADIUS = 0.01
# Emitted power = radiance · 4π²r² (~8, 6, 4 W per channel): about the Cornell ceiling
# light's power, which after the ceiling bounce leaves the room a little darker than the box.
BULB_RADIANCE = (2000.0, 1600.0, 1000.0)
SHADE_HEIGHT = 0.9
SHADE_HALF_SIZE = 0.12


def fireflies(frame: int = 0) -> dict:
    mi = mitsuba()
    scene = cornell_base()
    del scene["light"]
    scene["bulb"] = {
        "type": "sphere",
        "center": list(BULB_POSITION),
        "radius": BULB_RADIUS,
        "emitter": {"type": "area", "radiance": {"type": "rgb", "value": list(BULB_RADIANCE)}},
    }
    # A rectangle faces +z by default; rotate it to face up (two-sided so its top reflects onto
    # the ceiling and its underside is a dark disc seen from the room).
    scene["shade"] = {
        "type": "rectangle",
        "to_world": mi.ScalarTransform4f()
        .translate([BULB_POSITION[0], SHADE_HEIGHT, BULB_POSITION[2]])
        .rotate(axis=[1, 0, 0], angle=-90)
        .scale([SHADE_HALF_SIZE, SHADE_HALF_SIZE, 1]),
        "bsdf": {"type": "twosided", "bsdf": {"type": "ref", "id": "white"}},
    }
    return scene
