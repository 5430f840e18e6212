"""A scene loaded in one thread while another renders (the page's GET /scenes, a submit check
beside a running job) leaves the render intact: service/render/runtime.py's JIT_LOCK. Without
it 8 of 40 such 32² renders failed inside Dr.Jit ('operands have incompatible sizes', 'cannot
gather from a symbolic variable')."""
from __future__ import annotations

import threading

import numpy as np

from service.render.effects import inspect_scene
from service.render.framebuffer import FrameBuffer
from service.render.renderer import render_samples
from service.render.scenes import builtin_scene_names, film_size, load_scene

RENDERS = 30
SIZE = 32


def render_while_scenes_load(renders: int = RENDERS, timeout: float = 300.0) -> tuple[list[str], int]:
    """(the renders' errors, how many scene loads ran beside them). The renders run on a thread
    of their own so that a render that never returns (what the race also did, at 100 % CPU)
    fails the test instead of hanging it."""
    errors: list[str] = []
    loads = 0
    done = threading.Event()

    def load_every_builtin_scene() -> None:
        nonlocal loads
        while not done.is_set():
            for name in builtin_scene_names():
                film_size(name)
                inspect_scene(name)
                loads += 1

    def render_cornell_boxes() -> None:
        for seed in range(renders):
            scene = load_scene("cornell-box", width=SIZE, height=SIZE)
            buffer = FrameBuffer.empty(SIZE, SIZE)
            try:
                render_samples(scene, np.full((SIZE, SIZE), 16), buffer, seed=seed)
            except RuntimeError as exc:
                errors.append(str(exc))
                continue
            if not np.isfinite(buffer.mean).all() or buffer.mean.max() <= 0:
                errors.append(f"render {seed}: an empty or non-finite image")

    loader = threading.Thread(target=load_every_builtin_scene, daemon=True)
    renderer = threading.Thread(target=render_cornell_boxes, daemon=True)
    loader.start()
    renderer.start()
    renderer.join(timeout)
    done.set()
    if renderer.is_alive():
        errors.append(f"the renders did not finish within {timeout:.0f} s")
    else:
        loader.join(timeout)
    return errors, loads


def test_renders_stay_intact_while_another_thread_loads_scenes():
    errors, loads = render_while_scenes_load()
    assert loads > 0, "no scene load ran beside the renders: the test would prove nothing"
    assert errors == [], errors[:3]
