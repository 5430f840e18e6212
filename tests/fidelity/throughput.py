"""Throughput of render_samples vs mi.render at equal samples (not a test; run by hand):
    PYTHONPATH=$PWD python tests/fidelity/throughput.py
"""
import time, numpy as np
from service.render.runtime import mitsuba
from service.render.scenes import load_scene_info
from service.render.renderer import render_samples
from service.render.framebuffer import FrameBuffer
from tests.fidelity.harness import SCENES
mi = mitsuba()
SPP = 64
for name, size in [("path_gaussian.xml", 128), ("volpath_tent.xml", 128), ("direct_gaussian.xml", 128), ("path_box.xml", 128)]:
    li = load_scene_info(SCENES / name, width=size, height=size); sc = li.scene
    ref = li.scene
    def ours():
        b = FrameBuffer.empty(size, size); render_samples(sc, np.full((size, size), SPP), b, seed=3)
    def theirs():
        np.asarray(mi.render(ref, spp=SPP, seed=3))
    ours(); theirs()
    t_o = min((lambda t: (ours(), time.perf_counter() - t)[1])(time.perf_counter()) for _ in range(3))
    t_m = min((lambda t: (theirs(), time.perf_counter() - t)[1])(time.perf_counter()) for _ in range(3))
    print(f"{name:22s} {size}² × {SPP} spp: ours {t_o:.3f}s  mi.render {t_m:.3f}s  ratio(throughput) {t_m/t_o:.2f}", flush=True)
