"""Mitsuba's built-in Cornell box at a test's size and reconstruction filter, loaded."""
from __future__ import annotations

from service.render.runtime import mitsuba


def cornell_box(size: int, rfilter: str):
    mi = mitsuba()
    scene = mi.cornell_box()
    scene["sensor"]["film"].update(width=size, height=size, rfilter={"type": rfilter})
    return mi.load_dict(scene)
