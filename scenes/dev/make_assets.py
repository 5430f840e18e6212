"""Regenerate the small assets of the development scenes (meshes, textures, env map).

The outputs are committed; this script only documents how they were made and lets anyone
rebuild them byte-for-byte (fixed seeds). Needs numpy, pillow and OpenEXR.

    python scenes/dev/make_assets.py
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

HERE = Path(__file__).resolve().parent


# ---------------------------------------------------------------- meshes (binary PLY)
def write_ply(path: Path, positions: np.ndarray, normals: np.ndarray, faces: np.ndarray,
              uvs: np.ndarray | None = None) -> None:
    """Binary little-endian PLY with per-vertex normals (and uv), triangle faces."""
    props = ["x", "y", "z", "nx", "ny", "nz"] + (["u", "v"] if uvs is not None else [])
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(positions)}"]
    header += [f"property float {p}" for p in props]
    header += [f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    cols = [positions, normals] + ([uvs] if uvs is not None else [])
    verts = np.ascontiguousarray(np.concatenate(cols, axis=1).astype("<f4"))
    face_rec = np.zeros(len(faces), dtype=[("n", "u1"), ("i", "<i4", 3)])
    face_rec["n"] = 3
    face_rec["i"] = faces
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(verts.tobytes())
        f.write(face_rec.tobytes())


def grid_faces(nu: int, nv: int, wrap_u: bool, wrap_v: bool) -> np.ndarray:
    """Triangles of an nu x nv vertex grid (index = i*nv + j), optionally wrapping."""
    faces = []
    for i in range(nu if wrap_u else nu - 1):
        for j in range(nv if wrap_v else nv - 1):
            a = i * nv + j
            b = ((i + 1) % nu) * nv + j
            c = ((i + 1) % nu) * nv + (j + 1) % nv
            d = i * nv + (j + 1) % nv
            faces += [(a, b, c), (a, c, d)]
    return np.array(faces, dtype=np.int32)


def vertex_normals(pos: np.ndarray, faces: np.ndarray) -> np.ndarray:
    n = np.zeros_like(pos)
    fn = np.cross(pos[faces[:, 1]] - pos[faces[:, 0]], pos[faces[:, 2]] - pos[faces[:, 0]])
    for k in range(3):
        np.add.at(n, faces[:, k], fn)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def torus_knot(p: int = 2, q: int = 3, nu: int = 360, nv: int = 20, tube: float = 0.18):
    """A (p, q) torus knot tube, about 2.4 units across, centred at the origin."""
    t = np.linspace(0, 2 * np.pi, nu, endpoint=False)

    def curve(t):
        r = 2 + np.cos(q * t)
        return np.stack([r * np.cos(p * t), r * np.sin(p * t), -np.sin(q * t)], axis=1) * 0.4

    c = curve(t)
    tangent = curve(t + 1e-3) - curve(t - 1e-3)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    ref = np.array([0.0, 0.0, 1.0])
    n1 = np.cross(tangent, ref)
    n1 /= np.linalg.norm(n1, axis=1, keepdims=True)
    n2 = np.cross(tangent, n1)
    s = np.linspace(0, 2 * np.pi, nv, endpoint=False)
    ring = np.cos(s)[None, :, None] * n1[:, None, :] + np.sin(s)[None, :, None] * n2[:, None, :]
    pos = (c[:, None, :] + tube * ring).reshape(-1, 3)
    faces = grid_faces(nu, nv, True, True)
    # Winding so that normals point outwards.
    nrm = ring.reshape(-1, 3)
    fn = np.cross(pos[faces[:, 1]] - pos[faces[:, 0]], pos[faces[:, 2]] - pos[faces[:, 0]])
    if np.mean(np.sum(fn * nrm[faces[:, 0]], axis=1)) < 0:
        faces = faces[:, ::-1].copy()
    return pos, nrm, faces


def blob(subdiv_u: int = 96, subdiv_v: int = 48, seed: int = 7):
    """A lumpy, stone-like closed surface (UV sphere displaced by low-frequency bumps)."""
    rng = np.random.default_rng(seed)
    theta = np.linspace(0, np.pi, subdiv_v)
    phi = np.linspace(0, 2 * np.pi, subdiv_u, endpoint=False)
    th, ph = np.meshgrid(theta, phi)  # (nu, nv)
    d = np.stack([np.sin(th) * np.cos(ph), np.cos(th), np.sin(th) * np.sin(ph)], axis=-1)
    r = np.ones(th.shape)
    for _ in range(10):
        k = rng.normal(size=3)
        k /= np.linalg.norm(k)
        freq = rng.uniform(1.5, 4.0)
        r += 0.035 * np.sin(freq * (d @ k) * np.pi + rng.uniform(0, 2 * np.pi))
    pos = (d * r[..., None] * np.array([1.0, 0.8, 0.9])).reshape(-1, 3)
    faces = grid_faces(subdiv_u, subdiv_v, True, False)
    # Remove degenerate triangles at the poles.
    p = pos[faces]
    area = np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    faces = faces[area > 1e-10]
    if np.mean(np.sum(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])[area > 1e-10] * p[area > 1e-10, 0], axis=1)) < 0:
        faces = faces[:, ::-1].copy()
    return pos, vertex_normals(pos, faces), faces


def vase(nu: int = 96, nv: int = 48):
    """A lathed vase with a wall of finite thickness (outer and inner skin joined at the lip)."""
    h = np.linspace(0, 1, nv)
    outer = 0.35 + 0.18 * np.sin(np.pi * h * 1.2) - 0.12 * h
    inner = np.maximum(outer - 0.025, 0.02)
    prof_r = np.concatenate([outer, inner[::-1]])
    prof_y = np.concatenate([h, h[::-1].clip(0.03, None)])
    phi = np.linspace(0, 2 * np.pi, nu, endpoint=False)
    m = len(prof_r)
    pos = np.stack([prof_r[None, :] * np.cos(phi)[:, None], np.broadcast_to(prof_y, (nu, m)),
                    prof_r[None, :] * np.sin(phi)[:, None]], axis=-1).reshape(-1, 3)
    faces = grid_faces(nu, m, True, False)
    # close the bottom (outer) and the inner floor with fans
    centre_out = len(pos)
    centre_in = centre_out + 1
    pos = np.concatenate([pos, [[0, 0, 0], [0, 0.03, 0]]])
    fan = []
    for i in range(nu):
        a, b = i * m, ((i + 1) % nu) * m
        fan.append((centre_out, b, a))
        a2, b2 = i * m + m - 1, ((i + 1) % nu) * m + m - 1
        fan.append((centre_in, a2, b2))
    faces = np.concatenate([faces, np.array(fan, dtype=np.int32)])
    # orient outward: the outer skin's normals must point away from the axis
    p = pos[faces]
    fn = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    outer_faces = faces.max(axis=1) < centre_out
    radial = p[:, 0] * np.array([1, 0, 1])
    sel = outer_faces & (faces[:, 0] % m < nv - 1)
    if np.mean(np.sum(fn[sel] * radial[sel], axis=1)) < 0:
        faces = faces[:, ::-1].copy()
    return pos.astype(np.float32), vertex_normals(pos, faces), faces


# ---------------------------------------------------------------- textures (PNG)
def fine_print_texture(size: int = 512, seed: int = 3) -> Image.Image:
    """Newspaper-like page: columns of 1-2 px 'glyphs', rules, and a fine checker corner."""
    rng = np.random.default_rng(seed)
    img = np.full((size, size, 3), 232, np.uint8)
    img[..., 2] = 220  # slightly warm paper
    y = 10
    while y < size - 10:
        for col in range(3):
            x0 = 10 + col * (size - 20) // 3
            x1 = x0 + (size - 20) // 3 - 8
            x = x0
            while x < x1:
                w = int(rng.integers(2, 9))
                word = rng.random((4, w)) < 0.55
                img[y:y + 4, x:min(x + w, x1)][word[:, :max(0, min(w, x1 - x))]] = (25, 25, 30)
                x += w + 2
        y += int(rng.choice([6, 6, 6, 6, 12]))
    # headline bars and rules
    img[4:6, :] = 40
    img[size // 2:size // 2 + 1, :] = 60
    # a fine 2-px checker in the lower-right quarter
    yy, xx = np.mgrid[0:size // 4, 0:size // 4]
    checker = ((yy // 2 + xx // 2) % 2 == 0)
    block = img[-size // 4:, -size // 4:]
    block[checker] = (200, 40, 30)
    block[~checker] = (245, 240, 230)
    return Image.fromarray(img)


def wood_texture(w: int = 256, h: int = 256, seed: int = 5) -> Image.Image:
    """Floor planks: warm brown with grain streaks and dark plank seams."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    plank = (yy // 32).astype(int)
    offset = rng.uniform(0, 300, size=plank.max() + 1)[plank]
    grain = np.sin((xx + offset) * 0.05 + 3 * np.sin(yy * 0.2 + offset)) * 0.5 + 0.5
    grain = 0.75 + 0.25 * grain + rng.normal(0, 0.03, size=(h, w))
    tone = rng.uniform(0.85, 1.1, size=plank.max() + 1)[plank]
    base = np.array([0.55, 0.33, 0.18])
    rgb = base[None, None, :] * (grain * tone)[..., None]
    seam = (yy % 32) < 1
    seam |= ((xx + (plank % 2) * 128) % 256) < 1
    rgb[seam] *= 0.35
    return Image.fromarray((np.clip(rgb, 0, 1) ** (1 / 2.2) * 255).astype(np.uint8))


def rug_texture(size: int = 256) -> Image.Image:
    """A geometric rug: border bands and a diamond lattice."""
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float64) / size
    rgb = np.zeros((size, size, 3))
    rgb[:] = (0.45, 0.08, 0.07)
    diamond = (np.abs(((xx * 8) % 1) - 0.5) + np.abs(((yy * 8) % 1) - 0.5)) < 0.3
    rgb[diamond] = (0.75, 0.6, 0.35)
    edge = np.minimum(np.minimum(xx, 1 - xx), np.minimum(yy, 1 - yy))
    rgb[edge < 0.08] = (0.1, 0.12, 0.25)
    rgb[(edge > 0.04) & (edge < 0.05)] = (0.8, 0.75, 0.6)
    return Image.fromarray((rgb ** (1 / 2.2) * 255).astype(np.uint8))


def painting_texture(w: int = 128, h: int = 96, seed: int = 11) -> Image.Image:
    """A small abstract 'painting' for a picture frame."""
    img = Image.new("RGB", (w, h), (200, 180, 140))
    d = ImageDraw.Draw(img)
    rng = np.random.default_rng(seed)
    d.rectangle([0, 0, w, h * 0.55], fill=(110, 150, 190))
    for _ in range(12):
        x, y = rng.integers(0, w), rng.integers(h // 3, h)
        r = int(rng.integers(4, 18))
        c = tuple(int(v) for v in rng.integers(30, 220, 3))
        d.ellipse([x - r, y - r, x + r, y + r], fill=c)
    return img


# ---------------------------------------------------------------- environment map (EXR)
def studio_sky_env(w: int = 256, h: int = 128) -> np.ndarray:
    """Lat-long env (Mitsuba convention: +Y up, u along azimuth): sky gradient, warm ground,
    a small bright sun disc and one large soft 'window' panel. Linear RGB, float32."""
    v = (np.arange(h) + 0.5) / h
    u = (np.arange(w) + 0.5) / w
    theta = v * np.pi  # 0 = up
    phi = u * 2 * np.pi
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    d = np.stack([np.sin(th) * np.sin(ph), np.cos(th), -np.sin(th) * np.cos(ph)], axis=-1)
    up = d[..., 1]
    sky_top = np.array([0.18, 0.32, 0.70])
    sky_hor = np.array([0.75, 0.85, 1.00])
    ground = np.array([0.16, 0.13, 0.10])
    t = np.clip(up, 0, 1)[..., None] ** 0.5
    rgb = np.where(up[..., None] > 0, sky_hor * (1 - t) + sky_top * t, ground)
    sun_dir = np.array([0.55, 0.55, 0.63])
    sun_dir /= np.linalg.norm(sun_dir)
    cosang = d @ sun_dir
    sun = cosang > np.cos(np.radians(3.0))  # 3 degrees: a couple of texels at 256 x 128
    rgb[sun] = np.array([1.0, 0.92, 0.8]) * 400.0
    # soft glow around the sun
    glow = 2.0 * np.exp((cosang - 1) / 0.01) * (up > -0.05)
    rgb = rgb + glow[..., None] * np.array([1.0, 0.9, 0.7])
    return rgb.astype(np.float32)


def write_exr(path: Path, rgb: np.ndarray) -> None:
    import OpenEXR

    channels = {"RGB": np.ascontiguousarray(rgb.astype(np.float32))}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, channels) as f:
        f.write(str(path))


def main() -> None:
    write_ply(HERE / "env_object" / "knot.ply", *torus_knot())
    write_ply(HERE / "turntable" / "knot.ply", *torus_knot(p=3, q=4, nu=420, nv=16, tube=0.14))
    write_ply(HERE / "point_object" / "stone.ply", *blob())
    write_ply(HERE / "lamp_room" / "vase.ply", *vase())
    (HERE / "fine_texture").mkdir(exist_ok=True)
    fine_print_texture().save(HERE / "fine_texture" / "newspaper.png", optimize=True)
    (HERE / "living_room").mkdir(exist_ok=True)
    wood_texture().save(HERE / "living_room" / "wood.png", optimize=True)
    rug_texture().save(HERE / "living_room" / "rug.png", optimize=True)
    painting_texture().save(HERE / "living_room" / "painting.png", optimize=True)
    write_exr(HERE / "env_object" / "sky.exr", studio_sky_env())
    print("assets written under", HERE)


if __name__ == "__main__":
    main()
