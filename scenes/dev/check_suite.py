"""Load every development scene at low resolution, render it with `mi.render`, print stats.

    PYTHONPATH=. .venv/bin/python scenes/dev/check_suite.py OUT_DIR [--res 64] [--spp 16]
        [--only NAME ...] [--all-frames]

For each scene (each `scenes/dev/<name>/scene.xml`): load time, render time, mean linear
radiance, fraction of NaN/Inf pixels, fraction of black pixels, max value; a tonemapped PNG
(`<name>.png`, or `<name>_f<frame>.png` for sequences) goes to OUT_DIR, which must lie outside
the repository. The film is resized through the scene's own `<default>` parameters (`res`, or
`resx`/`resy` keeping the aspect ratio), so the scene files are used exactly as written.
Exit status 1 when any scene fails to load/render or produces NaN/Inf.
"""
from __future__ import annotations

import argparse
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
from PIL import Image

SUITE = Path(__file__).resolve().parent
REPO = SUITE.parents[1]


def declared_defaults(path: Path) -> dict[str, str]:
    """The `<default name=... value=...>` pairs declared at the top of a scene file."""
    return {e.get("name"): e.get("value") for e in ET.parse(path).getroot().iter("default")}


def scene_files(only: list[str] | None) -> list[Path]:
    files = sorted(SUITE.glob("*/scene.xml"))
    if only:
        files = [f for f in files if f.parent.name in only]
    return files


def sequence_length(defaults: dict[str, str]) -> int:
    """Animated scenes declare `frame` and the sequence length as `frames`."""
    return int(defaults.get("frames", "1")) if "frame" in defaults else 1


def load_params(defaults: dict[str, str], res: int, spp: int, frame: int | None) -> dict[str, str]:
    params = {"spp": str(spp)}
    if "res" in defaults:
        params["res"] = str(res)
    if "resx" in defaults and "resy" in defaults:
        w, h = int(defaults["resx"]), int(defaults["resy"])
        params["resx"] = str(res)
        params["resy"] = str(max(1, round(res * h / w)))
    if frame is not None:
        params["frame"] = str(frame)
    return params


def tonemap(img: np.ndarray) -> np.ndarray:
    """Clip to [0, 1] and apply the sRGB transfer curve (no exposure change)."""
    x = np.clip(np.nan_to_num(img, nan=0.0, posinf=1.0), 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return (srgb * 255 + 0.5).astype(np.uint8)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir", type=Path, help="folder for the PNGs (outside the repository)")
    parser.add_argument("--res", type=int, default=64, help="film width (height keeps the aspect)")
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--only", nargs="*", help="scene folder names to check")
    parser.add_argument("--all-frames", action="store_true", help="render every frame of sequences")
    args = parser.parse_args(argv)

    out = args.out_dir.resolve()
    if out == REPO or REPO in out.parents:
        parser.error(f"{out} is inside the repository; give a folder outside it")
    out.mkdir(parents=True, exist_ok=True)

    sys.path.insert(0, str(REPO))
    from service.render.runtime import mitsuba  # sets DRJIT_LIBLLVM_PATH before importing

    mi = mitsuba()
    print(f"variant {mi.variant()}, Mitsuba {mi.__version__}, {args.res} px wide, {args.spp} spp")
    header = f"{'scene':<16}{'frame':>6}{'size':>9}{'load s':>8}{'render s':>9}{'mean':>9}{'max':>10}{'nan/inf':>9}{'black':>7}"
    print(header)
    failed = False
    for path in scene_files(args.only):
        name = path.parent.name
        defaults = declared_defaults(path)
        n = sequence_length(defaults)
        frames = [None] if "frame" not in defaults else (range(n) if args.all_frames else sorted({0, n - 1}))
        for frame in frames:
            try:
                t0 = time.perf_counter()
                scene = mi.load_file(str(path), **load_params(defaults, args.res, args.spp, frame))
                t1 = time.perf_counter()
                img = np.array(mi.render(scene, spp=args.spp))
                t2 = time.perf_counter()
            except Exception as exc:  # report and go on with the other scenes
                print(f"{name:<16} FAILED: {' '.join(str(exc).split())[:300]}")
                failed = True
                continue
            rgb = img[..., :3]
            finite = np.isfinite(rgb).all(axis=-1)
            bad = 1.0 - finite.mean()
            black = float((rgb.max(axis=-1) <= 0).mean())
            mean = float(np.nanmean(np.where(np.isfinite(rgb), rgb, np.nan)))
            mx = float(np.nanmax(np.where(np.isfinite(rgb), rgb, np.nan)))
            size = f"{rgb.shape[1]}x{rgb.shape[0]}"
            tag = "" if frame is None else str(frame)
            print(f"{name:<16}{tag:>6}{size:>9}{t1 - t0:8.2f}{t2 - t1:9.2f}{mean:9.4f}{mx:10.2f}{bad:9.4f}{black:7.3f}")
            failed |= bad > 0
            png = out / (f"{name}.png" if frame is None else f"{name}_f{frame}.png")
            Image.fromarray(tonemap(rgb)).save(png)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
