"""Where a world point lands on a sensor's film, in pixels: the previous frame's half of a
motion vector (service/render/renderer.py).

Perspective and thin-lens cameras answer `Sensor.sample_direction` (ds.uv is the film position).
Mitsuba's orthographic camera does not implement it, so an animated orthographic scene failed
its first motion-vector pass. Its rays are parallel with origins affine in the film sample:
o(s) = O + s.x·A + s.y·B along one direction D. A world point p then solves
p − O = s.x·A + s.y·B + t·D, a 3×3 system solved once per render call from three of the
sensor's own rays.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import numpy as np


@dataclass
class FilmProjection:
    sensor: object
    crop: tuple[int, int]                  # film crop size (width, height) in pixels
    affine: tuple[np.ndarray, np.ndarray] | None = None   # (O, inverse of [A B D]) for parallel rays


def _answers_sample_direction(mi, sensor) -> bool:
    it = dr.zeros(mi.Interaction3f)
    it.p = mi.Point3f(0.0, 0.0, 1.0)
    try:
        sensor.sample_direction(it, mi.Point2f(0.5), True)
    except RuntimeError:
        return False
    return True


def film_projection(mi, sensor) -> FilmProjection:
    crop = tuple(int(c) for c in sensor.film().crop_size())
    if _answers_sample_direction(mi, sensor):
        return FilmProjection(sensor, crop)
    samples = mi.Point2f([0.0, 1.0, 0.0], [0.0, 0.0, 1.0])
    ray, _ = sensor.sample_ray(0.0, 0.5, samples, mi.Point2f(0.5))
    origins = np.asarray(ray.o, dtype=np.float64).reshape(3, -1)    # (xyz, sample)
    direction = np.asarray(ray.d, dtype=np.float64).reshape(3, -1)[:, 0]   # one for all rays
    columns = np.stack([origins[:, 1] - origins[:, 0], origins[:, 2] - origins[:, 0], direction], axis=1)
    return FilmProjection(sensor, crop, (origins[:, 0], np.linalg.inv(columns)))


def film_position(mi, projection: FilmProjection, world):
    """(film position in pixels, whether the point is in front of the sensor) for `world` points."""
    if projection.affine is None:
        it = dr.zeros(mi.Interaction3f)
        it.p = world
        ds, _ = projection.sensor.sample_direction(it, mi.Point2f(0.5), True)
        return ds.uv, ds.pdf > 0
    origin, inverse = projection.affine
    d = world - mi.Point3f(*(float(v) for v in origin))
    m = [[float(v) for v in row] for row in inverse]
    s = [m[r][0] * d.x + m[r][1] * d.y + m[r][2] * d.z for r in range(3)]
    uv = mi.Point2f(s[0] * projection.crop[0], s[1] * projection.crop[1])
    return uv, s[2] >= 0
