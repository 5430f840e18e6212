"""`renderloop bench --as-written`: the scenes exactly as published or written, each with its own
film filter and its film scaled to ~size² (aspect kept), scored against a high-spp `mi.render`
reference of the same file → docs/as-written.md with `-o docs`.

Per scene and seed, at `spp` samples per pixel: `mi.render` raw (the `hdrfilm` image a user gets),
`mi.render` + OIDN (albedo and normals from an `aov` integrator, the service's OIDN call) and the
render loop 16 → spp (error allocator, the shipped networks); SMAPE and relMSE of each, and the
loop's ratio to the better `mi.render` image. The pieces are the versus-mitsuba report's:
bench.versus_mitsuba_scene renders the competitor and the reference, bench.versus_mitsuba_run
builds the loop, bench.common scores and denoises.
"""
from __future__ import annotations

import argparse
import math
import statistics
import sys
from dataclasses import dataclass, field
from pathlib import Path

from bench.common import OidnDenoise, command_line, fill, fmt, image_metrics, load_bench_networks, oidn_denoiser, provenance
from bench.dev_references import DevScene, dev_scenes
from bench.versus_mitsuba_run import MITSUBA_SEED, make_loop, spp_levels
from bench.versus_mitsuba_scene import competitor_scene, reference, render_with_aovs, scaled_film, scene_filter
from models.pretrained import Networks
from service.render.runtime import active_variant

REPORT_NAME = "as-written.md"
DEFAULT_SIZE, DEFAULT_SPP, DEFAULT_REFERENCE_SPP = 128, 128, 4096
METHODS = ("mitsuba_raw", "mitsuba_oidn", "loop")
# The loop's final image is composed of these two (service.loop.final_image): reported beside it.
PARTS = ("loop_denoised", "loop_raw")
METRICS = ("smape", "relmse")
# The tutorials scenes as published (mitsuba-tutorials/scenes), by the file each one is.
TUTORIAL_FILES = {"cbox": "cbox.xml", "lego": "lego/scene.xml", "simple": "simple.xml"}
# Seeds of different methods must not share streams: the loop's seed s, mi.render's MITSUBA_SEED + this·s.
SEED_STRIDE = 100


@dataclass
class SceneResult:
    scene: DevScene
    source: str  # "tutorials" or "scenes/dev"
    rfilter: str
    film: str
    reference_spp: int
    # method → metric → one value per seed
    values: dict[str, dict[str, list[float]]] = field(default_factory=dict)

    def mean(self, method: str, metric: str) -> float:
        return statistics.fmean(self.values[method][metric])

    def better_mitsuba(self, metric: str) -> str:
        """The `mi.render` image with the lower mean of `metric`."""
        return min((m for m in METHODS if m != "loop"), key=lambda m: self.mean(m, metric))

    def ratio(self, metric: str) -> float:
        """The loop's value ÷ the better `mi.render` image's (< 1: the loop ahead)."""
        best = self.mean(self.better_mitsuba(metric), metric)
        return self.mean("loop", metric) / best if best > 0 else math.nan

    def seed_ratios(self, metric: str) -> list[float]:
        """Per seed, the loop's value ÷ that seed's image of the better `mi.render` method (by the
        mean): how much of `ratio` is one run's luck."""
        best = self.values[self.better_mitsuba(metric)][metric]
        return [loop / other if other > 0 else math.nan for loop, other in zip(self.values["loop"][metric], best)]

    @property
    def wins_every_seed(self) -> bool:
        """Whether the loop is ahead of the better `mi.render` image on each seed, in both metrics."""
        return all(r < 1 for metric in METRICS for r in self.seed_ratios(metric))

    @property
    def wins(self) -> bool:
        """Whether the loop beats both `mi.render` images in both metrics."""
        return all(self.ratio(metric) < 1 for metric in METRICS)


def tutorial_scenes(folder: Path) -> list[DevScene]:
    """The tutorials scenes present in `folder`, in TUTORIAL_FILES' order."""
    found = [DevScene(name, Path(folder) / file, 1) for name, file in TUTORIAL_FILES.items()
             if (Path(folder) / file).is_file()]
    if not found:
        raise ValueError(f"none of {', '.join(TUTORIAL_FILES.values())} under {folder}")
    return found


def score_scene(scene: DevScene, source: str, *, size: int, spp: int, reference_spp: int, seeds: list[int],
                networks: Networks, oidn: OidnDenoise, cache_dir: Path) -> SceneResult:
    """Every method on one scene, one run per seed, against its cached `mi.render` reference."""
    film = scaled_film(scene, size * size / 1e6)
    result = SceneResult(scene, source, scene_filter(scene), str(film), reference_spp,
                         {m: {k: [] for k in METRICS} for m in METHODS + PARTS})
    truth = reference(scene, film, reference_spp, cache_dir).mean
    competitor = competitor_scene(scene, film)
    for seed in seeds:
        rendered = render_with_aovs(competitor, spp, MITSUBA_SEED + SEED_STRIDE * seed)
        images = {"mitsuba_raw": rendered.color,
                  "mitsuba_oidn": oidn(rendered.color, rendered.albedo, rendered.normal),
                  **loop_images(scene, film, networks, spp, seed)}
        for method, image in images.items():
            scores = image_metrics(image, truth)
            for metric in METRICS:
                result.values[method][metric].append(scores[metric])
    return result


def loop_images(scene: DevScene, film, networks: Networks, spp: int, seed: int) -> dict:
    """The loop's final image after 16 → `spp` mean samples per pixel (error allocator), and the
    two it is composed of: its denoised image and the raw image of its samples."""
    loop = make_loop(scene, film, networks, "error", len(spp_levels(spp)), seed=seed)
    last = None
    for last in loop.run():
        pass
    return {"loop": last.denoised[0], "loop_denoised": loop.denoised_only()[0], "loop_raw": last.buffers[0].raw}


# --- the report -----------------------------------------------------------------------------------


def _cell(result: SceneResult, method: str, metric: str) -> str:
    text = fmt(result.mean(method, metric), ".4g")  # significant digits: relMSE goes down to 1e-5
    best = min(result.mean(m, metric) for m in METHODS)
    return f"**{text}**" if result.mean(method, metric) == best else text


def parts_table(results: list[SceneResult]) -> str:
    """The loop's final image beside the two it is composed of (SMAPE, relMSE)."""
    rows = ["| scene (filter) | denoised | raw (splatted) | final | denoised relMSE | raw relMSE | final relMSE |",
            "|---|---:|---:|---:|---:|---:|---:|"]
    for r in results:
        rows.append(f"| {r.source} {r.scene.name} ({r.rfilter}) | " + " | ".join(
            fmt(r.mean(m, metric), ".4g") for metric in METRICS for m in (*PARTS, "loop")) + " |")
    return "\n".join(rows)


def table(results: list[SceneResult], metric: str) -> str:
    rows = [f"| scene (filter) | film | `mi.render` raw | `mi.render` + OIDN | the loop | loop ÷ better `mi.render` |",
            "|---|---|---:|---:|---:|---:|"]
    for r in results:
        rows.append(f"| {r.source} {r.scene.name} ({r.rfilter}) | {r.film} | " +
                    " | ".join(_cell(r, m, metric) for m in METHODS) + f" | {fmt(r.ratio(metric), '.2f')} |")
    return "\n".join(rows)


def spread_section(results: list[SceneResult], seeds: list[int]) -> str:
    """With several seeds: per scene, the loop ÷ the better `mi.render` image on each seed (the
    tables above divide the means); empty for one seed."""
    if len(seeds) < 2:
        return ""
    steady = sum(r.wins_every_seed for r in results)
    rows = [f"| scene (filter) | SMAPE, seeds {', '.join(map(str, seeds))} | relMSE, seeds {', '.join(map(str, seeds))} |",
            "|---|---|---|"]
    for r in results:
        rows.append(f"| {r.source} {r.scene.name} ({r.rfilter}) | " + " | ".join(
            " ".join(fmt(v, ".2f") for v in r.seed_ratios(metric)) for metric in METRICS) + " |")
    return ("## The seeds' spread\n\nThe loop ÷ the better `mi.render` image (the one better on the mean), seed by "
            f"seed: ahead on every seed in both metrics on **{steady} of {len(results)}** scenes.\n\n" + "\n".join(rows) + "\n\n")


def report_text(results: list[SceneResult], *, size: int, spp: int, reference_spp: int, seeds: list[int],
                weights: str, oidn: str, command: str | None = None) -> str:
    wins = [r for r in results if r.wins]
    behind = ", ".join(f"{r.source} {r.scene.name}" for r in results if not r.wins) or "none"
    return fill("as_written.md", provenance=provenance(command or command_line(), active_variant()),
                size=size, spp=spp, reference_spp=reference_spp, seeds=", ".join(map(str, seeds)),
                weights=weights, oidn=oidn, smape_table=table(results, "smape"), relmse_table=table(results, "relmse"),
                parts_table=parts_table(results), spread_section=spread_section(results, seeds),
                wins=len(wins), total=len(results), behind=behind)


def run_as_written(out_dir: Path, *, tutorials: Path | None = None, size: int = DEFAULT_SIZE, spp: int = DEFAULT_SPP,
                   reference_spp: int = DEFAULT_REFERENCE_SPP, seeds: list[int] | None = None,
                   only: list[str] | None = None, weights_dir: Path | None = None, cache_dir: Path = Path("bench-cache"),
                   command: str | None = None) -> Path:
    """Measure the tutorials scenes (when `tutorials` is given) and scenes/dev (or those `only`
    named), write `out_dir`/as-written.md and return its path."""
    seeds = seeds or [0]
    scenes = [(s, "tutorials") for s in (tutorial_scenes(tutorials) if tutorials else [])]
    scenes += [(s, "scenes/dev") for s in dev_scenes()]
    if only:
        scenes = [(s, source) for s, source in scenes if s.name in only]
    nets = load_bench_networks(weights_dir)
    oidn, oidn_status = oidn_denoiser()
    out = Path(out_dir) / REPORT_NAME
    out.parent.mkdir(parents=True, exist_ok=True)
    results = []
    for scene, source in scenes:
        result = score_scene(scene, source, size=size, spp=spp, reference_spp=reference_spp, seeds=seeds,
                             networks=nets.networks, oidn=oidn, cache_dir=cache_dir)
        print(f"bench --as-written: {source} {scene.name} ({result.rfilter}, {result.film}): SMAPE " +
              ", ".join(f"{m} {result.mean(m, 'smape'):.4f}" for m in METHODS + PARTS), flush=True)
        results.append(result)
        # after every scene: a long run that is cut short still leaves the scenes it finished
        out.write_text(report_text(results, size=size, spp=spp, reference_spp=reference_spp, seeds=seeds,
                                   weights=nets.description, oidn=oidn_status, command=command))
    return out


# --- the command ------------------------------------------------------------------------------------


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The `renderloop bench` flags this report owns (--size, --spp, --reference-spp, --only, --weights,
    --cache and -o are shared with the other reports)."""
    parser.add_argument("--as-written", action="store_true",
                        help=f"the loop vs mi.render raw and mi.render + OIDN on the scenes as written (each its own "
                             f"filter, ~{DEFAULT_SIZE}², {DEFAULT_SPP} spp) → {REPORT_NAME}")
    parser.add_argument("--tutorials", type=Path, default=None, metavar="DIR",
                        help="with --as-written: also the published tutorials scenes in DIR (cbox.xml, lego/scene.xml, simple.xml)")
    parser.add_argument("--seeds", type=int, nargs="+", default=None, metavar="SEED",
                        help="with --as-written, --loop or --calibration: one run per seed (default 0); --as-written's "
                             "table gives their mean, --loop's and --calibration's their spread")


def run_as_written_command(args: argparse.Namespace) -> int:
    try:
        if args.tutorials is not None:
            tutorial_scenes(args.tutorials)
        spp_levels(args.spp or DEFAULT_SPP)
    except ValueError as exc:
        print(f"renderloop bench: error: {exc}", file=sys.stderr)
        return 2
    path = run_as_written(args.out, tutorials=args.tutorials, size=args.size or DEFAULT_SIZE,
                          spp=args.spp or DEFAULT_SPP, reference_spp=args.reference_spp or DEFAULT_REFERENCE_SPP,
                          seeds=args.seeds, only=args.only, weights_dir=args.weights, cache_dir=args.cache)
    print(f"wrote {path}")
    return 0
