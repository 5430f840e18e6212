"""Where a surface point was one frame earlier, on shapes that move between frames.

A motion vector (docs/exr.md) says where a pixel's first-hit point was on the previous
frame's film. Projecting the hit point with the previous frame's camera covers camera motion
only: a point on a turning object is somewhere else one frame earlier. `shape_motion` pairs the
shapes of two loaded frames and keeps, per moving shape, how to take a point back:

- a mesh (its vertices are stored in world space): the point's barycentric coordinates in its
  triangle, applied to the same triangle's vertices in the previous frame — rigid motion and
  deformation alike, as long as the mesh keeps its topology;
- an analytic shape (sphere, disk, cylinder, …): the affine map T_prev · T⁻¹ of its to_world.

Shapes are paired by kind, vertex and face counts and the nearest bounding box (`pair_shapes`);
a shape without a partner keeps camera-only motion. `previous_position` runs inside the render
kernel (service/render/renderer.py) on the primary hit.
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import numpy as np

STATIC, AFFINE, MESH = 0, 1, 2


@dataclass
class ShapeMotion:
    """Per slot (slot 0: static), indexed through `lookup` by the hit shape's registry id."""

    lookup: object          # mi.UInt32, registry id → slot
    kinds: object           # mi.UInt32 per slot: STATIC / AFFINE / MESH
    affine: object          # mi.Float, 12 per slot: rows of the 3×4 map to the previous frame
    face_offset: object     # mi.UInt32 per slot: the slot's first face in `faces`
    faces: object           # mi.UInt32, 3 per face: global vertex indices into the two arrays below
    vertices: object        # mi.Float, 3 per vertex: this frame's positions
    prev_vertices: object   # mi.Float, 3 per vertex: the previous frame's positions
    moving: int             # how many shapes move


def _registry_id(mi, shape) -> int:
    return int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shape))[0])


def _to_world(mi, shape) -> np.ndarray | None:
    params = mi.traverse(shape)
    if "to_world" not in params:
        return None
    return np.asarray(params["to_world"].matrix, dtype=np.float64).reshape(4, 4)


def _signature(shape) -> tuple:
    if shape.is_mesh():
        return ("mesh", shape.vertex_count(), shape.face_count())
    # the Python type of every analytic shape is `Shape`; its description names the plugin
    return ("shape", str(shape).split("[", 1)[0])


def _box(shape) -> np.ndarray:
    box = shape.bbox()
    return np.asarray([*box.min, *box.max], dtype=np.float64)


def pair_shapes(shapes: list, previous: list) -> list[tuple]:
    """(shape, its previous-frame self) pairs. Mitsuba does not promise one load order (mesh
    merging may reorder), so each shape takes, among the unpaired previous shapes of its kind and
    vertex/face counts, the one whose bounding box is nearest; a shape with none stays unpaired."""
    free = list(range(len(previous)))
    pairs = []
    for shape in shapes:
        candidates = [i for i in free if _signature(previous[i]) == _signature(shape)]
        if not candidates:
            continue
        here = _box(shape)
        best = min(candidates, key=lambda i: float(np.abs(_box(previous[i]) - here).sum()))
        free.remove(best)
        pairs.append((shape, previous[best]))
    return pairs


def shape_motion(mi, scene, prev_scene) -> ShapeMotion | None:
    """The motion of `scene`'s shapes since `prev_scene`; None when no shape moved."""
    slots_kind, slots_affine, slots_face = [STATIC], [np.zeros(12)], [0]
    ids, faces, vertices, prev_vertices = {}, [], [], []
    vertex_base = face_base = 0
    for shape, prev in pair_shapes(list(scene.shapes()), list(prev_scene.shapes())):
        if shape.is_mesh():
            now = np.asarray(shape.vertex_positions_buffer(), dtype=np.float32)
            before = np.asarray(prev.vertex_positions_buffer(), dtype=np.float32)
            if np.array_equal(now, before):
                continue
            tri = np.asarray(shape.faces_buffer(), dtype=np.uint32) + vertex_base
            ids[_registry_id(mi, shape)] = len(slots_kind)
            slots_kind.append(MESH)
            slots_affine.append(np.zeros(12))
            slots_face.append(face_base)
            faces.append(tri)
            vertices.append(now)
            prev_vertices.append(before)
            vertex_base += now.size // 3
            face_base += tri.size // 3
        else:
            now, before = _to_world(mi, shape), _to_world(mi, prev)
            if now is None or before is None or np.allclose(now, before, rtol=0, atol=1e-7):
                continue
            back = before @ np.linalg.inv(now)
            ids[_registry_id(mi, shape)] = len(slots_kind)
            slots_kind.append(AFFINE)
            slots_affine.append(back[:3].ravel())
            slots_face.append(0)
    if not ids:
        return None
    lookup = np.zeros(max(ids) + 1, dtype=np.uint32)
    for registry_id, slot in ids.items():
        lookup[registry_id] = slot

    def floats(parts: list[np.ndarray]):
        return mi.Float(np.concatenate(parts).astype(np.float32)) if parts else mi.Float(0.0)

    return ShapeMotion(
        lookup=mi.UInt32(lookup), kinds=mi.UInt32(np.asarray(slots_kind, dtype=np.uint32)),
        affine=floats(slots_affine), face_offset=mi.UInt32(np.asarray(slots_face, dtype=np.uint32)),
        faces=mi.UInt32(np.concatenate(faces)) if faces else mi.UInt32(0),
        vertices=floats(vertices), prev_vertices=floats(prev_vertices), moving=len(ids))


def _gather_point(mi, array, index, active):
    return mi.Point3f(*(dr.gather(mi.Float, array, index * 3 + k, active) for k in range(3)))


def previous_position(mi, motion: ShapeMotion, si, active):
    """The hit points `si.p` taken back to the previous frame (unchanged on static shapes)."""
    registry = dr.reinterpret_array(mi.UInt32, si.shape)
    known = active & (registry < dr.width(motion.lookup))
    slot = dr.gather(mi.UInt32, motion.lookup, registry, known)
    kind = dr.gather(mi.UInt32, motion.kinds, slot, known)
    p = si.p

    is_affine = known & (kind == AFFINE)
    row = [[dr.gather(mi.Float, motion.affine, slot * 12 + 4 * r + c, is_affine) for c in range(4)]
           for r in range(3)]
    moved = mi.Point3f(*(row[r][0] * p.x + row[r][1] * p.y + row[r][2] * p.z + row[r][3] for r in range(3)))

    is_mesh = known & (kind == MESH)
    face = dr.gather(mi.UInt32, motion.face_offset, slot, is_mesh) + si.prim_index
    corners = [dr.gather(mi.UInt32, motion.faces, face * 3 + k, is_mesh) for k in range(3)]
    v0, v1, v2 = (_gather_point(mi, motion.vertices, i, is_mesh) for i in corners)
    w0, w1, w2 = (_gather_point(mi, motion.prev_vertices, i, is_mesh) for i in corners)
    # Barycentric coordinates of p in (v0, v1, v2), least squares in the triangle's plane.
    e1, e2, d = v1 - v0, v2 - v0, p - v0
    d00, d01, d11 = dr.dot(e1, e1), dr.dot(e1, e2), dr.dot(e2, e2)
    d20, d21 = dr.dot(d, e1), dr.dot(d, e2)
    denom = d00 * d11 - d01 * d01
    ok = is_mesh & (dr.abs(denom) > 0)
    b1 = dr.select(ok, (d11 * d20 - d01 * d21) / denom, 0.0)
    b2 = dr.select(ok, (d00 * d21 - d01 * d20) / denom, 0.0)
    deformed = w0 * (1.0 - b1 - b2) + w1 * b1 + w2 * b2

    return dr.select(is_affine, moved, dr.select(ok, deformed, p))
