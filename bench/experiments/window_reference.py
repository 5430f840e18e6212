"""The ~2 MP suite re-scored on windows of the film against a reference of many more samples.

`renderloop bench --versus-mitsuba` scores each ~2 MP image against a 1024-spp reference whose own
relative error (0.0008–0.13 a scene) is about twice the loop's final SMAPE. SMAPE cannot go below it,
so the curves bunch at that floor: on the scenes the loop loses, its equal-time SMAPE ratio is
1.00–1.04 and a speed-up read there says as much of the reference's noise as of the images. A
whole-film reference with much less noise is hours a scene on this CPU; a grid of windows is not.
For each scene of the suite's newest CPU reading this renders a 3×3 grid of windows at
--window-spp samples (`independent`, cached in --cache), re-renders the images the report timed —
the loop (error allocator, the report's seed) and each `mi.render` + OIDN film at each level (its
seed) — and scores them on the windows' pixels together, a margin dropped where a window's own
render lacks its neighbours' splats. The times stay the report's, the competitors re-timed as on
docs/competitor-features.md where they wrapped their features. Beside each image's window scores
stand its whole-film SMAPE against the cached 1024-spp reference as the report printed it and as
re-rendered here: equal, they say the images scored are the ones that were timed. The readings are
the suite page's (bench.versus_mitsuba_run.better_of, least_at_competitor_ends) on the windows.

    python -m bench.experiments.window_reference [--scenes A B] [--window-spp 8192] [--reports docs]
        [--costs-from docs/competitor-features.md] [--scores-from FILE] [--cache bench-cache] [-o FILE]

`--scores-from` keeps the scores an earlier run's report holds for a scene whose newest reading is
still the one it scored, and renders only the rest (of --scenes; `--scenes` with no names renders
nothing: the page regenerated from those scores).
"""
from __future__ import annotations

import argparse
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from bench.common import (Reference, experiment_command, load_bench_networks, oidn_denoiser, pinned_torch_threads,
                          provenance, publish)
from bench.experiments.competitor_features import (SuiteReadings, costs_from_report, film_kind, readings_summary,
                                                   speedup_text, suite_curves, suite_readings)
from bench.experiments.crop_reference import MARGIN, scored
from bench.loop_report import DEFAULT_CACHE_DIR
from bench.versus_mitsuba import suite_scenes
from bench.versus_mitsuba_report import LOOP_LABEL
from bench.versus_mitsuba_run import MITSUBA_SEED, Curve, CurvePoint, debiased_relmse, image_smape, make_loop
from bench.versus_mitsuba_scene import (Crop, Film, competitor_scene, reference, reference_path, render_with_aovs)
from bench.versus_mitsuba_suite import Reading, cpu_standing, suite_names, table_rows

GRID = 3              # windows per side: their centres at the centres of a 3×3 split of the film
WINDOW = (112, 84)    # pixels of each window (4:3, as most suite films); 9 of them are 4 % of 2 MP
WINDOW_SPP = 8192     # 8× the whole-film reference's samples: its noise ÷ 2.8
FULL_REFERENCE_SPP = 1024
SCORES_HEADER = ("| scene | report | method | spp | s | SMAPE as printed | re-rendered | windows SMAPE "
                 "| windows relMSE |")


def grid_crops(film: Film, grid: int = GRID, size: tuple[int, int] = WINDOW) -> list[Crop]:
    """grid × grid windows of `size`, centred on the centres of a grid × grid split of the film."""
    width, height = size
    return [Crop(round(film.width * (i + 0.5) / grid) - width // 2, round(film.height * (j + 0.5) / grid) - height // 2,
                 width, height) for j in range(grid) for i in range(grid)]


def pooled(windows: list[np.ndarray]) -> np.ndarray:
    """The windows' scored pixels (margin dropped) as one (1, N, 3) image."""
    return np.concatenate([scored(w).reshape(-1, 3) for w in windows])[None]


def pooled_reference(references: list[Reference]) -> Reference:
    return Reference(pooled([r.mean for r in references]), pooled([r.variance for r in references]))


@dataclass(frozen=True)
class PointScore:
    """One timed image of a report, re-rendered and scored."""
    scene: str
    report: str
    method: str           # the curve's key in the report (LOOP_LABEL or a `mi.render` + OIDN film)
    spp: int
    seconds: float        # as the suite reads it (re-timed where the competitor wrapped its features)
    printed_smape: float  # the report's, whole film against the 1024-spp reference
    full_smape: float     # the re-rendered image's, the same way (nan without that reference cached)
    window_smape: float
    window_relmse: float  # the windows' reference's noise taken out (debiased_relmse)


def window_images(scene, film: Film, networks, competitors: list[Curve],
                  levels: list[int]) -> dict[tuple[str, int], np.ndarray]:
    """(method, spp) → the whole-film image the report timed: the loop's at each iteration (its
    seed, error allocator), and each competitor film's `mi.render` + OIDN at each level."""
    images = {}
    for record in make_loop(scene, film, networks, "error", len(levels)).run():
        images[(LOOP_LABEL, round(record.spp_mean))] = np.array(record.denoised[0], copy=True)
    oidn, _ = oidn_denoiser()
    for curve in competitors:
        loaded = competitor_scene(scene, film, box=film_kind(curve.key) == "box")
        for spp in levels:
            image = render_with_aovs(loaded, spp, MITSUBA_SEED)
            images[(curve.key, spp)] = oidn(image.color, image.albedo, image.normal)
    return images


def scene_scores(reading: Reading, curves: list[Curve], window_spp: int, cache: Path, networks) -> list[PointScore]:
    """Every point of the report's loop and competitor curves, re-rendered and scored."""
    (scene,) = suite_scenes([reading.scene])
    film = Film(*(int(v) for v in reading.film.split(",")[0].split("×")))
    crops = grid_crops(film)
    strong = pooled_reference([reference(scene, film, window_spp, cache, crop) for crop in crops])
    full = (reference(scene, film, FULL_REFERENCE_SPP, cache).mean
            if reference_path(scene, film, FULL_REFERENCE_SPP, cache).is_file() else None)
    levels = [round(p.spp) for p in curves[0].points]
    images = window_images(scene, film, networks, [c for c in curves if c.key != LOOP_LABEL], levels)
    scores = []
    for curve in curves:
        for point in curve.points:
            image = images[(curve.key, round(point.spp))]
            windows = pooled([crop.of(image) for crop in crops])
            scores.append(PointScore(reading.scene, reading.report, curve.key, round(point.spp), point.seconds,
                                     point.smape, image_smape(image, full) if full is not None else math.nan,
                                     image_smape(windows, strong.mean), debiased_relmse(windows, strong)))
    return scores


def window_curves(curves: list[Curve], scores: list[PointScore]) -> list[Curve]:
    """`curves` (the report's times) with each point's errors the windows'."""
    by_point = {(s.method, s.spp): s for s in scores}

    def rescored(key: str, point: CurvePoint) -> CurvePoint:
        score = by_point[(key, round(point.spp))]
        return replace(point, smape=score.window_smape, relmse=score.window_relmse)

    return [Curve(c.key, c.label, [rescored(c.key, p) for p in c.points]) for c in curves]


@dataclass(frozen=True)
class SceneWindows:
    reading: Reading
    scores: list[PointScore]
    whole: SuiteReadings      # the report's curves
    windows: SuiteReadings    # the same times, the windows' errors
    reproduced: float        # the largest |re-rendered ÷ printed − 1| of its whole-film SMAPEs (nan: unchecked)


def scene_windows(reading: Reading, curves: list[Curve], scores: list[PointScore]) -> SceneWindows:
    loop, competitors = curves[0], curves[1:]
    rewindowed = window_curves(curves, scores)
    checked = [abs(s.full_smape / s.printed_smape - 1) for s in scores if math.isfinite(s.full_smape)]
    return SceneWindows(reading, scores, suite_readings(loop, competitors),
                        suite_readings(rewindowed[0], rewindowed[1:]),
                        max(checked) if checked else math.nan)


def scores_from_report(path: Path) -> list[PointScore]:
    """The per-point table of an earlier run's report (its -o file)."""
    scores = []
    for cells in table_rows(path.read_text().splitlines(), SCORES_HEADER):
        scene, report, method = cells[:3]
        numbers = [math.nan if cell in ("—", "nan") else float(cell.rstrip("s ")) for cell in cells[3:]]
        scores.append(PointScore(scene, report, method, int(numbers[0]), *numbers[1:]))
    return scores


def _number(value: float, spec: str) -> str:
    return "—" if math.isnan(value) else format(value, spec)


def report_text(rows: list[SceneWindows], command: str, window_spp: int) -> str:
    lines = ["# The ~2 MP suite on windows against a stronger reference", "", provenance(command), "",
             " ".join(__doc__.split("\n\n")[1].split()), "",
             f"Windows: {GRID}×{GRID} of {WINDOW[0]}×{WINDOW[1]} pixels, {MARGIN} px of margin dropped, "
             f"references of {window_spp} spp. Speed-ups over the better competitor (`~`: read off its "
             "fitted power law); at the competitors' last points, the least favourable film. \"Whole film\": "
             "the suite page's reading against the 1024-spp reference. \"Reproduced\": the largest difference "
             "between a re-rendered image's whole-film SMAPE and the report's (printed to 4 significant digits); "
             "\"unchecked\" where the scene's 1024-spp reference is not in the cache.",
             "", "| scene (film) | report | reproduced | SMAPE speed-up, whole film | windows | relMSE, whole film "
             "| windows | at the competitors' last points, whole film | windows |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for row in rows:
        reproduced = "unchecked" if math.isnan(row.reproduced) else f"{100 * row.reproduced:.2f} %"
        cells = [f"{row.reading.scene} ({row.reading.film})", row.reading.report, reproduced,
                 speedup_text(*row.whole.smape), speedup_text(*row.windows.smape), speedup_text(*row.whole.relmse),
                 speedup_text(*row.windows.relmse), f"{row.whole.end:.2f}×", f"{row.windows.end:.2f}×"]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", f"Over {len(rows)} scenes, " + readings_summary(
        "whole film", "windows", ([r.whole.smape[0] for r in rows], [r.windows.smape[0] for r in rows]),
        ([r.whole.relmse[0] for r in rows], [r.windows.relmse[0] for r in rows]),
        ([r.whole.end for r in rows], [r.windows.end for r in rows])), "",
        "## Every image", "", SCORES_HEADER, "|---|---|---|---:|---:|---:|---:|---:|---:|"]
    for row in rows:
        for s in row.scores:
            lines.append(f"| {s.scene} | {s.report} | {s.method} | {s.spp} | {s.seconds:.2f} | "
                         f"{s.printed_smape:.4g} | {_number(s.full_smape, '.4g')} | {s.window_smape:.5f} | "
                         f"{s.window_relmse:.4g} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", nargs="*", default=None,
                        help="the suite scenes to render (default: every one with a CPU reading; none: only "
                             "--scores-from's)")
    parser.add_argument("--window-spp", type=int, default=WINDOW_SPP)
    parser.add_argument("--reports", type=Path, default=Path("docs"))
    parser.add_argument("--costs-from", type=Path, default=Path("docs/competitor-features.md"),
                        help="the competitors' feature costs (bench.experiments.competitor_features' report)")
    parser.add_argument("--scores-from", type=Path, default=None, help="an earlier run's report: keep its scores")
    parser.add_argument("--cache", type=Path, default=DEFAULT_CACHE_DIR)
    parser.add_argument("-o", "--out", type=Path, default=None, help="write the report here too")
    args = parser.parse_args(argv)
    standing = cpu_standing(args.reports)
    costs = costs_from_report(args.costs_from)
    earlier = scores_from_report(args.scores_from) if args.scores_from and args.scores_from.is_file() else []
    networks = None
    rows = []
    for name in suite_names():
        reading = standing.newest.get(name)
        kept = [s for s in earlier if s.scene == name and reading is not None and s.report == reading.report]
        if reading is None or not (kept or args.scenes is None or name in args.scenes):
            continue
        loop, competitors = suite_curves(reading, args.reports / reading.report, costs)
        curves = [loop, *competitors]
        if not kept:
            if networks is None:
                networks = load_bench_networks(None).networks
            with pinned_torch_threads(2), torch.no_grad():
                kept = scene_scores(reading, curves, args.window_spp, args.cache, networks)
        row = scene_windows(reading, curves, kept)
        rows.append(row)
        print(f"{name}: SMAPE speed-up {speedup_text(*row.whole.smape)} -> {speedup_text(*row.windows.smape)} on "
              f"windows; relMSE {speedup_text(*row.whole.relmse)} -> {speedup_text(*row.windows.relmse)}", flush=True)
    command = experiment_command("bench.experiments.window_reference", argv)
    text = report_text(rows, command, args.window_spp)
    publish(text, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
