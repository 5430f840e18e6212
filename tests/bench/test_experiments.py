"""bench/experiments (the measurements behind shipped settings): a swept setting must act only
where it is measured, or it would leak into the next measurement (and into the product)."""
from __future__ import annotations

import argparse
import importlib
import re
from dataclasses import replace
import pkgutil
from pathlib import Path

import numpy as np
import pytest
import torch

import bench.experiments
from bench.common import denoiser_settings, image_metrics, load_bench_networks
from bench.quality_measures import block_means
from bench.experiments.competitor_features import (FeatureCost, costs_from_report, feature_cost, reread, report_text,
                                                   retimed, source_timings)
from bench.experiments import freed_memory, network_passes_bound, window_reference
from bench.experiments.crop_reference import quarter_crops, scored, window_scores
from bench.experiments.energy_tolerance import UNTOUCHED, median_pixel_ratio, outputs_per_tolerance
from bench.experiments.gate_offset import offset_ratios
from bench.experiments.seed_spread import paired_ratio
from bench.experiments.setting_sweep import parse_values, setting_images, summary_rows
from bench.versus_mitsuba import suite_scenes
from bench.versus_mitsuba_run import Curve, CurvePoint
from bench.versus_mitsuba_scene import Film
from bench.versus_mitsuba_suite import Reading
from models.denoiser import Denoiser, DenoiserConfig
from models.frames import FrameTensors
from service.loop.tensors import to_image


def random_frame(size: int, seed: int = 0) -> FrameTensors:
    g = torch.Generator().manual_seed(seed)
    rand = lambda c: torch.rand(1, c, size, size, generator=g)   # noqa: E731
    return FrameTensors(color=rand(3) * 2, variance=rand(3) * 0.1, albedo=rand(3) * 0.8 + 0.1,
                        normal=rand(3) * 2 - 1, depth=rand(1) + 1, motion=None, spp=torch.full((1, 1, size, size), 16.0))


@torch.no_grad()
def test_gate_offset_sweep_scores_each_setting_and_leaves_the_denoisers_config_as_it_was():
    # energy restoration off: it would move the output away from the candidate it is compared with
    config = DenoiserConfig(width=8, spatial_blocks=1, temporal=False, oidn_candidate=True, energy_tolerance=0.0)
    denoiser = Denoiser(config).eval()
    g = torch.Generator().manual_seed(0)
    frame = FrameTensors(color=torch.rand(1, 3, 16, 16, generator=g), variance=torch.rand(1, 3, 16, 16, generator=g) * 0.1,
                         albedo=torch.full((1, 3, 16, 16), 0.5), normal=torch.rand(1, 3, 16, 16, generator=g),
                         depth=torch.ones(1, 1, 16, 16), motion=None)
    candidate = torch.rand(1, 3, 16, 16, generator=g)
    reference = to_image(candidate) * 1.1
    oidn = image_metrics(to_image(candidate), reference)
    settings = [(0.0, 0.0, False, None), (10.0, 10.0, False, None), (0.0, 0.0, True, None), (0.0, 0.0, False, 0.0)]
    ratios = offset_ratios(denoiser, frame, candidate, reference, oidn, settings)
    assert denoiser.config == config
    assert len(ratios) == 4 and ratios[0] != ratios[1] and ratios[0] != ratios[2]
    np.testing.assert_allclose(ratios[3], (1.0, 1.0), rtol=1e-4)   # a zero-width clamp: the kernels become OIDN
    np.testing.assert_allclose(ratios[1], (1.0, 1.0), rtol=0.05)   # b = 10 everywhere: OIDN's image back


def test_energy_tolerance_sweep_pulls_towards_the_samples_only_as_tau_grows_and_restores_the_config():
    # gate offset 10: the output is the candidate's image, whatever the untrained kernels do
    config = DenoiserConfig(width=8, spatial_blocks=1, temporal=False, oidn_candidate=True, energy_tolerance=0.03,
                            gate_offset=10.0)
    torch.manual_seed(0)
    denoiser = Denoiser(config).eval()
    g = torch.Generator().manual_seed(0)
    color = torch.rand(1, 3, 16, 16, generator=g)
    frame = FrameTensors(color=color, variance=torch.full((1, 3, 16, 16), 1e-8), albedo=torch.full((1, 3, 16, 16), 0.5),
                         normal=torch.rand(1, 3, 16, 16, generator=g), depth=torch.ones(1, 1, 16, 16), motion=None)
    candidate = color * 0.8                       # a denoiser that lost a fifth of the energy
    with torch.no_grad():
        cache = denoiser.prepare([frame], 0, candidate)
        untouched, pulled = outputs_per_tolerance(denoiser, cache, [UNTOUCHED, 1.0])
    assert denoiser.config == config
    samples_mean = float(color.mean())
    assert untouched.mean() == pytest.approx(0.8 * samples_mean, rel=0.02)  # left as the network made it
    assert pulled.mean() == pytest.approx(samples_mean, rel=1e-3)         # rse ≪ τ: the samples' total


def test_the_median_pixel_ratio_reads_the_typical_pixel_where_the_total_reads_the_brightest():
    reference = np.full((10, 10, 3), 0.1, np.float32)
    reference[0, 0] = 100.0                       # one bright pixel holds most of the energy
    image = reference * 1.03
    image[0, 0] = 50.0                            # a denoiser that lost half of it, a gain that lifted the rest 3 %
    assert image.sum() / reference.sum() < 0.6
    assert median_pixel_ratio(image, reference) == pytest.approx(1.03, rel=1e-5)


def test_pooling_shows_the_bias_a_heavy_tailed_references_typical_pixel_hides():
    # a reference of rare-path light: log-normal per pixel, mean 1 but median 0.88. Per pixel, SMAPE
    # against it prefers an image that lost 8 % of the energy; over 32×32 block means the
    # reference's noise has averaged out and the unbiased image wins.
    rng = np.random.default_rng(0)
    sigma = 0.5
    reference = np.exp(rng.normal(-sigma ** 2 / 2, sigma, (256, 256, 3)))
    unbiased, dark = np.ones_like(reference), np.full_like(reference, 0.92)
    per_pixel = [image_metrics(x, reference)["smape"] for x in (unbiased, dark)]
    pooled = [image_metrics(block_means(x, 32), block_means(reference, 32))["smape"] for x in (unbiased, dark)]
    assert per_pixel[1] < per_pixel[0]
    assert pooled[0] < pooled[1] / 3


def test_quarter_crops_lie_inside_the_film_apart_and_score_without_their_margin():
    film = Film(1633, 1225)
    crops = quarter_crops(film)
    assert len(crops) == 4
    for a in crops:
        assert 0 <= a.x and a.x + a.width <= film.width and 0 <= a.y and a.y + a.height <= film.height
        for b in crops:
            assert a == b or a.x + a.width <= b.x or b.x + b.width <= a.x or a.y + a.height <= b.y or b.y + b.height <= a.y
    image = np.arange(1225 * 1633 * 3, dtype=np.float32).reshape(1225, 1633, 3)
    window = crops[0].of(image)
    assert window.shape == (96, 128, 3) and window[0, 0, 0] == image[crops[0].y, crops[0].x, 0]
    assert scored(window).shape == (88, 120, 3)
    reference = [np.full((96, 128, 3), 0.5)] * 2
    smape, relmse, median = window_scores([np.full((96, 128, 3), 0.55)] * 2, reference)
    assert median == pytest.approx(1.1) and smape == pytest.approx(0.05 / 1.06, rel=1e-3) and relmse > 0


def test_setting_sweep_over_energy_block_restores_each_half_where_it_was_lost_and_restores_the_config():
    # gate offset 10: the output is the candidate's image; the candidate lost a fifth on its left half only
    config = DenoiserConfig(width=8, spatial_blocks=1, temporal=False, oidn_candidate=True, energy_tolerance=0.03,
                            gate_offset=10.0)
    torch.manual_seed(0)
    denoiser = Denoiser(config).eval()
    color = torch.ones(1, 3, 32, 32)
    frame = FrameTensors(color=color, variance=torch.full((1, 3, 32, 32), 1e-10), albedo=torch.full((1, 3, 32, 32), 0.5),
                         normal=torch.zeros(1, 3, 32, 32), depth=torch.ones(1, 1, 32, 32), motion=None)
    candidate = color.clone()
    candidate[..., :16] *= 0.8
    with torch.no_grad():
        image_wide, blocks = setting_images(denoiser, frame, candidate, "energy_block", [0, 8])
    assert denoiser.config == config
    assert image_wide[:, 24:].mean() > 1.05                               # one factor: the right half overshoots
    np.testing.assert_allclose(blocks[:, 24:], 1.0, rtol=0.01)            # block by block: both halves right
    np.testing.assert_allclose(blocks[:, :8], 1.0, rtol=0.01)


def test_denoiser_settings_apply_inside_and_are_undone_even_when_the_measurement_fails():
    denoiser = Denoiser(DenoiserConfig(width=8, spatial_blocks=1, temporal=False, oidn_candidate=True)).eval()
    config = denoiser.config
    with pytest.raises(RuntimeError):
        with denoiser_settings(denoiser, gate_offset=3.0, kernel_clamp=0.5):
            assert (denoiser.config.gate_offset, denoiser.config.kernel_clamp) == (3.0, 0.5)
            raise RuntimeError("a measurement failed")
    assert denoiser.config == config


def test_paired_ratio_settles_a_consistent_lead_and_calls_a_seed_to_seed_swing_a_tie():
    consistent = paired_ratio([0.98, 0.97, 0.99, 0.98], [1.0, 1.0, 1.0, 1.0])
    assert consistent.verdict == "ours" and consistent.wins == 4 and consistent.geometric_mean == pytest.approx(0.98, abs=0.002)
    assert (consistent.low, consistent.high) == pytest.approx((0.97, 0.99))
    swinging = paired_ratio([0.95, 1.05, 0.96, 1.04], [1.0, 1.0, 1.0, 1.0])
    assert swinging.verdict == "tie" and swinging.wins == 2
    behind = paired_ratio([1.03, 1.02, 1.04], [1.0, 1.0, 1.0])
    assert behind.verdict == "OIDN" and behind.t > 2 and behind.wins == 0
    assert paired_ratio([1.0, 1.0], [1.0, 1.0]).t == 0.0           # identical: no spread, no verdict


def test_setting_sweep_reads_each_value_as_the_settings_own_type():
    assert parse_values("albedo_floor", ["0", "0.1"]) == [0.0, 0.1]
    assert all(type(v) is float for v in parse_values("albedo_floor", ["0", "0.1"]))
    assert parse_values("energy_block", ["0", "32"]) == [0, 32]
    assert all(type(v) is int for v in parse_values("energy_block", ["32"]))
    assert parse_values("kernel_clamp", ["off", "0.5"]) == [None, 0.5]
    assert parse_values("candidate_cap", ["on", "off"]) == [True, False]
    with pytest.raises(ValueError):
        parse_values("energy_block", ["0.5"])


def test_setting_sweep_summary_takes_medians_counts_and_their_mean_per_value():
    # two scenes at one spp; value 1 is at most OIDN's on one scene in SMAPE and both in relMSE
    cells = {(16, 0): [(1.2, 1.1), (1.0, 0.9)], (16, 1): [(0.9, 0.8), (1.1, 0.7)]}
    rows = summary_rows(cells, [16], [0, 1])
    assert rows[0] == (0, [(1.1, 1, 1.0, 1)], pytest.approx(1.05))
    assert rows[1] == (1, [(1.0, 1, 0.75, 2)], pytest.approx(0.875))


def test_setting_sweep_images_follow_the_setting_and_restore_the_config():
    config = DenoiserConfig(width=8, spatial_blocks=1, temporal=False, oidn_candidate=True)
    torch.manual_seed(0)
    denoiser = Denoiser(config).eval()
    albedo = torch.full((1, 3, 16, 16), 0.8)
    albedo[..., :8] = 0.0
    color = torch.where(albedo > 0, 0.8, 1.0)
    frame = FrameTensors(color=color, variance=torch.full_like(color, 1e-4), albedo=albedo,
                         normal=torch.zeros(1, 3, 16, 16), depth=torch.ones(1, 1, 16, 16), motion=None)
    with torch.no_grad():
        plain, floored, plain_again = setting_images(denoiser, frame, color.clone(), "albedo_floor", [0.0, 0.1, 0.0])
    assert denoiser.config == config
    np.testing.assert_array_equal(plain, plain_again)
    assert np.abs(plain - floored).max() > 1e-3


KEPT_EXPERIMENTS = ("accumulation_rules", "competitor_calls", "competitor_features", "crop_reference",
                    "energy_tolerance", "exposure_range", "freed_memory", "gate_offset", "mitsuba_exr_denoise",
                    "network_passes_bound", "seed_spread", "setting_sweep", "static_flicker", "window_reference")


def test_the_kept_experiments_import_against_the_current_product_and_no_others_crept_in():
    """Each kept experiment re-decides a shipped setting, so a product change that breaks its imports
    (a renamed function, a removed option) must fail here, not at the next re-run; a new one-off
    script needs a decision behind it (docs/decisions.md) and a place in this list."""
    found = sorted(m.name for m in pkgutil.iter_modules(bench.experiments.__path__))
    assert found == sorted(KEPT_EXPERIMENTS)
    for name in found:
        module = importlib.import_module(f"bench.experiments.{name}")
        assert callable(module.main), name


def _curve(key: str, points: list[tuple[int, float, float]]) -> Curve:
    return Curve(key, key, [CurvePoint(spp, seconds, smape, {}, smape / 100) for spp, seconds, smape in points])


def test_a_retimed_competitor_scales_its_render_time_keeps_its_oidn_call_and_can_lose_the_loop_its_lead(tmp_path):
    cost = FeatureCost(wrapped=20.0, plain=9.0, features=1.0, oidn=2.0)
    competitor = _curve("`mi.render` + OIDN, box film", [(16, 22.0, 0.030), (32, 42.0, 0.027), (64, 82.0, 0.025)])
    loop = _curve("the loop (error allocator)", [(16, 15.0, 0.029), (32, 30.0, 0.027), (64, 60.0, 0.025)])
    assert cost.ratio == 0.5
    assert [p.seconds for p in retimed(competitor, cost).points] == [12.0, 22.0, 42.0]
    reading = Reading("sun_room", "1633×1225, gaussian", 0.025, 1.37, False, "0.9×", 1.37, 0.02, 5000.0,
                      "benchmarks-versus-mitsuba.md", "abc1234", "2026-11-28", "16–64 spp")
    row = reread(reading, loop, [competitor], {competitor.key: cost})
    assert row.before[0] == pytest.approx(82.0 / 60.0) and row.after[0] == pytest.approx(42.0 / 60.0)
    assert row.end_before == pytest.approx(82.0 / 60.0) and row.end_after == pytest.approx(42.0 / 60.0)
    # the report's cost table reads back as the costs that made it (--costs-from)
    # a reading whose competitor already rendered its features apart is not re-timed
    apart = reread(replace(reading, scene="metals", features_apart=True), loop, [competitor], {})
    assert apart.after == apart.before and apart.end_after == apart.end_before
    path = tmp_path / "costs.md"
    path.write_text(report_text([row, apart], "python -m x --spp 2", "the median of 3 renders."))
    assert costs_from_report(path) == {"sun_room": {"box": cost}}
    assert "re-timed **ahead on 1 of 2, median 1.03×**" in path.read_text()
    # a re-read from that table names where its costs were measured, however many re-reads ago
    first = source_timings(path)
    assert first.startswith("from `python -m x --spp 2` (") and first.endswith("the median of 3 renders.")
    again = tmp_path / "again.md"
    again.write_text(report_text([row], "python -m x --costs-from costs.md", f"{first}"))
    assert source_timings(again) == first


def test_the_feature_cost_renders_and_times_every_kind_and_the_oidn_call_on_the_competitors_scene():
    # a smoke test of the rendering path (the timings themselves are the experiment's to read)
    (scene,) = suite_scenes(["hard_shadows"])
    cost = feature_cost(scene, Film(48, 36), box=False, spp=4, repeats=2)
    assert min(cost.wrapped, cost.plain, cost.features, cost.oidn) > 0


def test_freed_memory_report_reads_each_allocators_iterations_after_the_first():
    """The first iteration builds Dr.Jit's kernels, so it must not move the medians; faults and RSS per allocator."""
    def run(first: float, later: list[float], faults: int) -> dict:
        timings = [{"render": first, "denoise": first, "error": first, "allocate": 0.0}]
        timings += [{"render": s, "denoise": s / 2, "error": s / 4, "allocate": 0.1} for s in later]
        return {"timings": timings, "wall": first + sum(later), "faults": faults, "peak_rss_mb": 5000.0, "film": "8x8"}

    defaults = [run(99.0, [4.0, 8.0, 6.0], 900_000), run(99.0, [4.0, 8.0, 6.0], 1_100_000)]
    kept = [run(99.0, [2.0, 2.0, 3.0], 1_000), run(99.0, [2.0, 2.0, 3.0], 3_000)]
    assert freed_memory.stage_medians(defaults) == {"render": 6.0, "denoise": 3.0, "error": 1.5, "allocate": 0.1}
    args = argparse.Namespace(scenes="s", megapixels=2.0, iterations=4, repeats=2, output=None)
    text = freed_memory.report({"s": {"defaults": defaults, "kept": kept}}, args)
    assert "| s (8x8) | defaults | 6.00 | 3.00 | 1.50 | 0.10 | 117.00 | 1,000,000 | 5000 |" in text
    assert "| s (8x8) | kept | 2.00 | 1.00 | 0.50 | 0.10 | 106.00 | 2,000 | 5000 |" in text
    assert "python -m bench.experiments.freed_memory --scenes s" in text


def test_one_pass_a_point_charges_every_render_so_far_and_only_its_own_iterations_networks():
    loop = _curve("the loop (error allocator)", [(16, 6.0, 0.03), (32, 13.0, 0.02), (64, 24.0, 0.015)])
    stages = [{"render": 4.0, "denoise": 1.5, "error": 0.5, "allocate": 0.0},
              {"render": 4.5, "denoise": 2.0, "error": 0.3, "allocate": 0.2},
              {"render": 8.0, "denoise": 2.5, "error": 0.4, "allocate": 0.1}]
    bound = network_passes_bound.one_pass_per_point(loop, stages)
    assert [p.seconds for p in bound.points] == pytest.approx([6.0, 4.0 + 4.7 + 2.3, 4.0 + 4.7 + 8.1 + 2.9])
    assert [p.smape for p in bound.points] == [p.smape for p in loop.points]   # the images as measured
    with pytest.raises(ValueError, match="3 curve points but 2 stage rows"):
        network_passes_bound.one_pass_per_point(loop, stages[:2])


def test_the_stage_table_reads_one_scenes_iterations_of_a_report():
    lines = ["## The loop's stages, per iteration", "", network_passes_bound.STAGE_HEADER,
             "|---|---:|---:|---:|---:|---:|---:|---:|",
             "| a | 0 | 16 | 4.079 | 2.011 | 0.298 | 0.000 | 6.39 |",
             "| b | 0 | 16 | 1.262 | 1.837 | 0.259 | 0.000 | 3.36 |",
             "| a | 1 | 32 | 4.342 | 2.276 | 0.299 | 0.112 | 7.03 |", ""]
    assert network_passes_bound.stage_seconds(lines, "a") == [
        {"render": 4.079, "denoise": 2.011, "error": 0.298, "allocate": 0.0},
        {"render": 4.342, "denoise": 2.276, "error": 0.299, "allocate": 0.112}]


def test_the_bound_reads_the_suite_as_measured_exactly_as_the_competitor_re_read_does(tmp_path):
    """Its 'as measured' column must be the suite re-read's re-timed one (the same curves, costs and
    readings), and freeing the intermediate passes can only bring the loop's point times forward."""
    out = tmp_path / "bound.md"
    network_passes_bound.main(["-o", str(out)])
    bound_text = out.read_text()
    features = (Path("docs") / "competitor-features.md").read_text()
    measured = re.search(r"SMAPE: as measured (ahead on \d+ of \d+, median [0-9.]+×)", bound_text).group(1)
    assert f"re-timed **{measured}**" in features
    rows = [line.split(" | ") for line in bound_text.splitlines() if line.startswith("| ") and "benchmarks-" in line]
    assert len(rows) == 21 and all(float(r[3]) <= float(r[2]) for r in rows)


def test_the_window_grid_lies_inside_the_film_its_windows_apart_and_centred_on_its_ninths():
    film = Film(1633, 1225)
    crops = window_reference.grid_crops(film)
    assert len(crops) == 9 and all((c.width, c.height) == window_reference.WINDOW for c in crops)
    for a in crops:
        assert 0 <= a.x and a.x + a.width <= film.width and 0 <= a.y and a.y + a.height <= film.height
        for b in crops:
            assert a == b or a.x + a.width <= b.x or b.x + b.width <= a.x or a.y + a.height <= b.y or b.y + b.height <= a.y
    assert (crops[4].x + crops[4].width // 2, crops[4].y + crops[4].height // 2) == (816, 612)
    windows = [np.full((84, 112, 3), float(i)) for i in range(9)]
    assert window_reference.pooled(windows).shape == (1, 9 * 76 * 104, 3)   # the margins dropped


def _scores(curves: list[Curve], windows: dict[str, list[float]]) -> list:
    return [window_reference.PointScore("s", "r.md", c.key, round(p.spp), p.seconds, p.smape, p.smape,
                                        windows[c.key][i], round(windows[c.key][i] / 100, 6))
            for c in curves for i, p in enumerate(c.points)]


def test_windows_can_turn_a_reading_the_whole_films_noisy_reference_bunched_and_its_table_reads_back(tmp_path):
    """At the 1024-spp reference's floor the competitor reaches the loop's SMAPE at once; on the windows,
    where the loop's image is twice as good, it needs a far longer time: the same curves' times, other errors."""
    loop = _curve("the loop (error allocator)", [(16, 10.0, 0.0200), (32, 20.0, 0.0199)])
    competitor = _curve("`mi.render` + OIDN, box film", [(16, 8.0, 0.0201), (32, 16.0, 0.0199)])
    scores = _scores([loop, competitor], {loop.key: [0.010, 0.007], competitor.key: [0.020, 0.014]})
    reading = Reading("s", "64×48, box", 0.0199, 0.8, False, "1.0×", 0.8, 0.02, 5000.0, "r.md", "abc1234",
                      "2026-11-30", "16–32 spp")
    row = window_reference.scene_windows(reading, [loop, competitor], scores)
    assert row.whole.smape[0] == pytest.approx(16.0 / 20.0)
    assert row.windows.smape[0] == pytest.approx(3.08, abs=0.01) and row.windows.smape[1] == "extrapolated"
    assert row.windows.end == pytest.approx(16.0 / 10.0)   # the loop's first point already below 0.014
    assert row.reproduced == 0.0
    rewindowed = window_reference.window_curves([loop, competitor], scores)
    assert [p.seconds for p in rewindowed[1].points] == [8.0, 16.0]
    assert [p.smape for p in rewindowed[0].points] == [0.010, 0.007]
    path = tmp_path / "windows.md"
    path.write_text(window_reference.report_text([row], "python -m x", 8192))
    assert window_reference.scores_from_report(path) == scores
    assert "windows **ahead on 1 of 1" in path.read_text()


def test_the_window_images_are_the_loops_iterations_and_each_competitor_films_levels():
    (scene,) = suite_scenes(["hard_shadows"])
    film = Film(48, 36)
    competitor = _curve("`mi.render` + OIDN, the scene's filter", [(16, 1.0, 0.1), (32, 2.0, 0.1)])
    images = window_reference.window_images(scene, film, load_bench_networks(None).networks, [competitor], [16, 32])
    assert sorted(images) == sorted([("the loop (error allocator)", 16), ("the loop (error allocator)", 32),
                                     (competitor.key, 16), (competitor.key, 32)])
    assert all(image.shape == (36, 48, 3) and np.isfinite(image).all() for image in images.values())
