"""The development suite at K× its film size (`--film-scale K`; K = 2, about 512², writes
benchmarks-dev-x2.md): references rendered at that size into the cache and found by it,
and the loop run at it."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bench.dev_references import (load_reference, reference_file, scaled_film, scaled_reference_dir, dev_scenes,
                                  write_references)
from bench.loop_report import dev_settings, run_loop_benchmark, scene_reference_image
from bench.loop_run import DEV, loop_spec, METHODS, prepare_scenes

POINT_OBJECT = "point_object"   # the suite's cheapest scene (256×256, mostly background)


@pytest.fixture(scope="module")
def scaled_cache(tmp_path_factory) -> Path:
    cache = tmp_path_factory.mktemp("cache")
    write_references(scaled_reference_dir(cache, 2), spp=4, only=[POINT_OBJECT], film_scale=2)
    return cache


def test_scaled_references_are_rendered_at_k_times_the_film_and_found_by_their_size(scaled_cache):
    (scene,) = dev_scenes([POINT_OBJECT])
    assert scaled_film(scene, 2) == (512, 512)
    path = reference_file(scaled_reference_dir(scaled_cache, 2), POINT_OBJECT, 512, 512, 4, None)
    assert path.is_file()
    image, header = load_reference(scaled_reference_dir(scaled_cache, 2), scene, size=(512, 512))
    assert image.shape == (512, 512, 3) and np.isfinite(image).all() and image.mean() > 0
    assert header["film_scale"] == 2 and header["spp"] == 4
    with pytest.raises(FileNotFoundError, match="--film-scale"):
        load_reference(scaled_reference_dir(scaled_cache, 2), scene, size=(256, 256))


def test_the_scaled_loop_renders_at_the_scaled_film_against_the_scaled_reference(scaled_cache):
    settings = dev_settings(2, reference_spp=4)
    assert settings.film_scale == 2 and dev_settings(1) is DEV
    (scene,) = prepare_scenes(settings, scaled_cache, [POINT_OBJECT])
    assert scene.film == (512, 512)
    spec = loop_spec(scene, METHODS[0], settings, iterations=1)
    assert (spec.width, spec.height) == (512, 512)
    assert scene_reference_image(scene, settings, scaled_cache).shape == (512, 512, 3)
    with pytest.raises(FileNotFoundError, match="--reference-spp 4096"):   # a reference of another spp
        scene_reference_image(scene, dev_settings(2), scaled_cache)


def test_film_scale_outside_the_development_suite_is_refused_in_one_line(tmp_path):
    result = subprocess.run([sys.executable, "-m", "service.cli", "bench", "--loop", "--film-scale", "2", "-o",
                             str(tmp_path)], capture_output=True, text=True, timeout=300)
    assert result.returncode == 2 and "--suite dev" in result.stderr and "Traceback" not in result.stderr


@pytest.mark.slow
def test_scaled_development_loop_benchmark_writes_its_own_report(scaled_cache, tmp_path, tiny_weights_dir):
    report = run_loop_benchmark(tmp_path, weights_dir=tiny_weights_dir, cache_dir=scaled_cache, suite="dev",
                                only=[POINT_OBJECT], film_scale=2, reference_spp=4,
                                command="renderloop bench --loop --suite dev --film-scale 2")
    text = report.read_text()
    assert report.name == "benchmarks-dev-x2.md" and "$" not in text
    assert "about 512²" in text and "4 spp" in text and "| point_object |" in text


def test_a_scaled_loop_without_its_references_names_the_command_that_makes_them(tmp_path):
    result = subprocess.run([sys.executable, "-m", "service.cli", "bench", "--loop", "--suite", "dev", "--film-scale",
                             "3", "--only", POINT_OBJECT, "--cache", str(tmp_path), "-o", str(tmp_path)],
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "renderloop bench --references --film-scale K (a 768x768 film)" in result.stderr
