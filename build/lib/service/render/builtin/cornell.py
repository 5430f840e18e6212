"""Cornell box variants built on Mitsuba's own `mi.cornell_box()` dictionary."""
from __future__ import annotations

import math

from service.render.runtime import mitsuba

# The camera of mi.cornell_box() sits on the +z axis looking at the box centre.
CORNELL_CAMERA_DISTANCE = 3.9
CORNELL_TARGET = (0.0, 0.0, 0.0)
CORNELL_MAX_DEPTH = 8

# Orbit: a sine swing rather than a steady rotation, so any frame count keeps the camera in
# front of the open side of the box; frame 0 is exactly the static view.
ORBIT_AMPLITUDE_DEG = 10.0
ORBIT_PERIOD_FRAMES = 48


def cornell_base() -> dict:
    """A fresh `mi.cornell_box()` dict (a new one each call: callers edit it in place)."""
    scene = mitsuba().cornell_box()
    scene["integrator"] = {"type": "path", "max_depth": CORNELL_MAX_DEPTH}
    return scene


def cornell_box(frame: int = 0) -> dict:
    """Static: every frame is the same scene."""
    return cornell_base()


def orbit_angle_deg(frame: int) -> float:
    return ORBIT_AMPLITUDE_DEG * math.sin(2.0 * math.pi * frame / ORBIT_PERIOD_FRAMES)


def cornell_box_orbit(frame: int = 0) -> dict:
    mi = mitsuba()
    scene = cornell_base()
    angle = math.radians(orbit_angle_deg(frame))
    origin = [CORNELL_CAMERA_DISTANCE * math.sin(angle), 0.0, CORNELL_CAMERA_DISTANCE * math.cos(angle)]
    scene["sensor"]["to_world"] = mi.ScalarTransform4f().look_at(
        origin=origin, target=list(CORNELL_TARGET), up=[0.0, 1.0, 0.0]
    )
    return scene
