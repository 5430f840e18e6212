"""Interiors lit through an opening: a closed room with a window in one wall, lit only by a sun
and sky outside (issue 13's "an interior lit through an opening by sun and sky").

The procedural rooms are lit from inside and open at the front, so they never show what such an
interior does to a denoiser: a sharp, very bright sun patch on the floor next to walls lit only
indirectly, i.e. noisy, dim surfaces beside hard-edged light. The room here is closed on all
four sides (the camera stays inside), one wall is cut into four panels around a rectangular
opening, and the sky's sun is turned so that it shines in through it: light reaches the room
only through the opening.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from service.dataset.textures import SkySpec

Vec3 = tuple[float, float, float]

WINDOW_WALLS = ("back", "left", "right")
# Each wall: centre x and z as multiples of the room's (width, depth) halves, the rotation about
# +Y that turns a unit rectangle's +Z normal into the room, and which half-extent spans it.
_WALLS = {
    "back": ((0.0, -1.0), 0.0, "width"),
    "left": ((-1.0, 0.0), 90.0, "depth"),
    "right": ((1.0, 0.0), -90.0, "depth"),
    "front": ((0.0, 1.0), 180.0, "width"),
}
# The sun's azimuth (textures.sky_image's convention: direction to the sun is (cos e·sin a,
# sin e, −cos e·cos a)) that points straight out of each window wall.
_OUTWARD_AZIMUTH = {"back": 0.0, "left": -math.pi / 2, "right": math.pi / 2}
SUN_ELEVATION_DEG = (15.0, 50.0)   # low enough that the patch lands inside the room, on the floor
SUN_SPREAD_DEG = 50.0              # azimuth off the window's normal, either side
SILL = 0.5                         # lowest bottom edge of the opening above the floor
EDGE = 0.2                         # wall left on each side of the opening and above it
CAMERA_MARGIN = 0.15
# The sky's sun is set for an irradiance of ~3 in the open (procedural._sky); through a window
# the room's walls see only indirect light from a patch, which left half of the first rooms
# tried at a mean radiance below 0.01 (black to the eye): 3× brings them to a lit-room range.
SUN_GAIN = 3.0


@dataclass(frozen=True)
class WindowSpec:
    wall: str                   # one of WINDOW_WALLS
    centre: tuple[float, float]  # (u, v): along the wall from its middle, and height above the floor
    half: tuple[float, float]    # half width, half height of the opening


def sample_window(rng: np.random.Generator, room: Vec3) -> WindowSpec:
    width, height, depth = room
    wall = WINDOW_WALLS[int(rng.integers(len(WINDOW_WALLS)))]
    span = width if wall == "back" else depth
    half_w = float(rng.uniform(0.3, max(0.31, min(0.9, span / 2 - EDGE - 0.1))))
    half_h = float(rng.uniform(0.3, max(0.31, min(0.7, (height - SILL - EDGE) / 2))))
    u = float(rng.uniform(-span / 2 + EDGE + half_w, span / 2 - EDGE - half_w))
    v = float(rng.uniform(SILL + half_h, max(SILL + half_h, height - EDGE - half_h)))
    return WindowSpec(wall=wall, centre=(u, v), half=(half_w, half_h))


def sun_through(rng: np.random.Generator, window: WindowSpec, sky: SkySpec) -> SkySpec:
    """`sky` with its sun outside `window`, low enough to shine in and onto the floor."""
    spread = math.radians(SUN_SPREAD_DEG)
    azimuth = _OUTWARD_AZIMUTH[window.wall] + float(rng.uniform(-spread, spread))
    elevation = math.radians(float(rng.uniform(*SUN_ELEVATION_DEG)))
    return dataclasses.replace(sky, sun_azimuth=azimuth, sun_elevation=elevation,
                               sun_radiance=sky.sun_radiance * SUN_GAIN)


def closed_room_bounds(room: Vec3) -> tuple[Vec3, Vec3]:
    """Camera box inside all four walls (the procedural rooms' box reaches out of the open front)."""
    width, height, depth = room
    m = CAMERA_MARGIN
    return (-width / 2 + m, m, -depth / 2 + m), (width / 2 - m, height - m, depth / 2 - m)


def _panel(mi, wall: str, room: Vec3, u: tuple[float, float], v: tuple[float, float]):
    """to_world of the rectangle covering [u0, u1] × [v0, v1] of `wall` (v from the floor)."""
    width, height, depth = room
    (cx, cz), angle, _ = _WALLS[wall]
    return (mi.ScalarTransform4f().translate([cx * width / 2, height / 2, cz * depth / 2])
            .rotate([0.0, 1.0, 0.0], angle)
            .translate([(u[0] + u[1]) / 2, (v[0] + v[1]) / 2 - height / 2, 0.0])
            .scale([(u[1] - u[0]) / 2, (v[1] - v[0]) / 2, 1.0]))


def wall_panels(mi, room: Vec3, window: WindowSpec, bsdf: dict) -> dict[str, dict]:
    """The window wall as four panels around the opening, plus the closing front wall."""
    width, height, depth = room
    span = width if _WALLS[window.wall][2] == "width" else depth
    (u, v), (hw, hh) = window.centre, window.half
    u0, u1, v0, v1 = u - hw, u + hw, v - hh, v + hh
    pieces = {"left": ((-span / 2, u0), (0.0, height)), "right": ((u1, span / 2), (0.0, height)),
              "below": ((u0, u1), (0.0, v0)), "above": ((u0, u1), (v1, height))}
    shapes = {f"wall_{window.wall}_{name}": {"type": "rectangle", "to_world": _panel(mi, window.wall, room, pu, pv),
                                             "bsdf": bsdf}
              for name, (pu, pv) in pieces.items() if pu[1] - pu[0] > 1e-6 and pv[1] - pv[0] > 1e-6}
    shapes.update(front_wall(mi, room, bsdf))
    return shapes


def front_wall(mi, room: Vec3, bsdf: dict) -> dict[str, dict]:
    """The wall the procedural rooms leave open for the camera, closing the room."""
    width, height, _ = room
    return {"wall_front": {"type": "rectangle", "bsdf": bsdf,
                           "to_world": _panel(mi, "front", room, (-width / 2, width / 2), (0.0, height))}}
