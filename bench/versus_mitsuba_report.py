"""The report of `renderloop bench --versus-mitsuba`: what one run gathered, and its tables (the
prose is bench/templates/versus_mitsuba.md)."""
from __future__ import annotations

import math
import statistics
from dataclasses import dataclass, field
from pathlib import Path

from bench.common import BenchNetworks, fill, fmt, load_average, provenance
from bench.dev_references import DevScene
from bench.loop_run import EXTRAPOLATION_LIMIT
from bench.versus_mitsuba_costs import STAGES as COST_STAGES, FixedCosts
from bench.versus_mitsuba_run import Comparison, Curve, EndReading, Reading, least_at_competitor_ends
from bench.versus_mitsuba_scene import AOVS, COMPETITOR_CALL_LANES, Film
from service.render.runtime import active_variant

LOOP, UNIFORM = "loop", "uniform"
LOOP_LABEL = "the loop (error allocator)"  # its column in the curve tables
# The bars the loop is held to against mi.render on the CPU at ~2 MP: ahead on at least 75 % of
# the scenes, a median 1.5× speed-up at equal error, a peak resident memory within 8 GB.
GOAL_SHARE_AHEAD, GOAL_MEDIAN_SPEEDUP, GOAL_PEAK_RSS_GB = 0.75, 1.5, 8.0
FULL_COMMAND = "renderloop bench --versus-mitsuba -o docs"  # the defaults: 2 MP, 16…1024 spp, 4096-spp references
FULL_MEGAPIXELS = 2.0  # what "the full figures" means
# The table read at each competitor's last point; `--versus-mitsuba-suite` finds it by this header.
END_HEADER = "| scene (film, filter) | `mi.render` + OIDN at its last point |"
LOOP_STAGES = ("render", "denoise", "error", "allocate")


@dataclass
class SceneRun:
    scene: DevScene
    film: Film
    rfilter: str
    reference_error: float  # the reference's mean relative standard error
    curves: dict[str, Curve]  # "mitsuba", "mitsuba-box" (unless the film is box already), LOOP, UNIFORM
    versus_mitsuba: Comparison  # the loop against the better mi.render + OIDN
    versus_uniform: Comparison
    costs: FixedCosts
    versus_mitsuba_relmse: Comparison | None = None  # the same, in relMSE less the reference's noise


@dataclass
class Settings:
    megapixels: float
    max_spp: int
    reference_spp: int
    threads: int
    command: str
    cache_dir: Path
    subset: tuple[str, ...] = ()  # the scenes named by --scenes; empty: the whole suite


@dataclass
class CostProbe:
    """One 16-spp iteration of the loop (error allocator) at --costs-megapixels, no reference: the
    fixed costs and the memory at a size the curves were not run at."""

    scene: str
    film: Film
    costs: FixedCosts
    peak_rss_mb: float
    rss_growth_mb: float


@dataclass
class Results:
    settings: Settings
    nets: BenchNetworks
    oidn_status: str
    load_before: str
    scenes: list[SceneRun] = field(default_factory=list)
    seconds: float = math.nan
    probe: CostProbe | None = None


# --- cells ------------------------------------------------------------------------------------------


# How a Reading is marked in a cell: `~` a power law's guess, `≤` bounded by the curve's first point.
READING_MARKS = {"extrapolated": "~", "at most": "≤"}


def reading_cell(reading: Reading, spec: str) -> str:
    if not math.isfinite(reading.value):
        return "never"
    return READING_MARKS.get(reading.how, "") + format(reading.value, spec)


def ratio_cell(value: float, reading: Reading) -> str:
    """A ratio whose numerator is `reading` (a time or an error), marked as the reading is."""
    if not math.isfinite(value):
        return "n/a"
    return READING_MARKS.get(reading.how, "") + f"{value:.2f}×"


def scene_cell(run: SceneRun) -> str:
    return f"{run.scene.name} ({run.film}, {run.rfilter})"


# --- tables ------------------------------------------------------------------------------------------


def headline_table(scenes: list[SceneRun]) -> str:
    lines = ["| scene (film, filter) | loop SMAPE | loop s | better `mi.render` + OIDN | its s to that SMAPE | "
             "equal-error speed-up | equal-time SMAPE ratio | vs uniform + ours | loop peak RSS MB |",
             "|---|---:|---:|---|---:|---:|---:|---:|---:|"]
    for run in scenes:
        v, u = run.versus_mitsuba, run.versus_uniform
        which = run.curves[v.other].label
        lines.append(f"| {scene_cell(run)} | {v.target:.4f} | {v.loop_seconds:.2f} | {which} | "
                     f"{reading_cell(v.other_seconds, '.2f')} | **{ratio_cell(v.speedup, v.other_seconds)}** | "
                     f"{ratio_cell(v.error_ratio, v.other_error)} | {ratio_cell(u.speedup, u.other_seconds)} | "
                     f"{fmt(run.curves[LOOP].peak_rss_mb, '.0f')} |")
    return "\n".join(lines)


def summary(scenes: list[SceneRun], megapixels: float) -> str:
    if not scenes:
        return "No scenes ran."
    speedups = [run.versus_mitsuba.speedup for run in scenes]
    ahead = sum(s > 1 for s in speedups)
    measured = sum(run.versus_mitsuba.other_seconds.measured for run in scenes)
    median = statistics.median(speedups)
    peak_gb = max(c.peak_rss_mb for run in scenes for k, c in run.curves.items() if k == LOOP) / 1024
    share = ahead / len(scenes)
    at_size = ("" if megapixels >= FULL_MEGAPIXELS * 0.9 else
               f" (the bars are for ~{FULL_MEGAPIXELS:g} MP; this run is at {megapixels:g} MP, so they are "
               "stated for reference, not met or missed)")
    return (f"The loop reaches the better `mi.render` + OIDN's error in less wall time on **{ahead} of {len(scenes)}** "
            f"scenes ({share:.0%}; bar ≥ {GOAL_SHARE_AHEAD:.0%}); median equal-error speed-up **{median:.2f}×** "
            f"(bar ≥ {GOAL_MEDIAN_SPEEDUP:g}×, goal 2×); {measured} of {len(scenes)} speed-ups are read inside the "
            f"measured curves, the others extrapolated (`~`). The loop's peak RSS: **{peak_gb:.2f} GB** at most "
            f"(bar ≤ {GOAL_PEAK_RSS_GB:g} GB for a 2 MP job){at_size}.")


def competitor_curves(run: SceneRun) -> list[Curve]:
    return [c for key, c in run.curves.items() if key.startswith("mitsuba")]


def end_reading(run: SceneRun) -> EndReading:
    return least_at_competitor_ends(run.curves[LOOP], competitor_curves(run))


def end_cells(reading: EndReading) -> tuple[str, str]:
    """(the loop's seconds, the speed-up) as printed: `≤`/`≥` for a bound from the loop's first
    point, `~` for an extrapolated time, "never" where the loop's curve does not fall that low."""
    seconds = reading.loop_seconds
    if not math.isfinite(seconds.value):
        return "never", "0×"
    mark = {"at most": ("≤", "≥"), "extrapolated": ("~", "~")}.get(seconds.how, ("", ""))
    return f"{mark[0]}{seconds.value:.2f}", f"{mark[1]}{reading.speedup:.2f}×"


def end_table(scenes: list[SceneRun]) -> str:
    lines = [END_HEADER + " its SMAPE | its s | the loop's s to that SMAPE | speed-up there |",
             "|---|---|---:|---:|---:|---:|"]
    for run in scenes:
        reading = end_reading(run)
        loop_seconds, speedup = end_cells(reading)
        lines.append(f"| {scene_cell(run)} | {run.curves[reading.other].label} | {reading.target:.4g} | "
                     f"{reading.other_seconds:.2f} | {loop_seconds} | **{speedup}** |")
    return "\n".join(lines)


def end_summary(scenes: list[SceneRun]) -> str:
    readings = [end_reading(run) for run in scenes]
    if not readings:
        return ""
    ahead = sum(r.speedup > 1 for r in readings)
    measured = sum(r.measured for r in readings)
    return (f"At the competitors' own last points the loop gets there sooner on **{ahead} of {len(readings)}** "
            f"scenes, median **{statistics.median(r.speedup for r in readings):.2f}×**; {measured} of "
            f"{len(readings)} readings need no extrapolation (read between two points of the loop's curve, or "
            f"bounded by its first: `≥`).")


def relmse_table(scenes: list[SceneRun]) -> str:
    """The headline read in relMSE with the reference's own noise taken out (`debiased_relmse`)."""
    lines = ["| scene (film, filter) | reference's relative error | loop relMSE | better `mi.render` + OIDN | "
             "its s to that relMSE | equal-error speed-up | equal-time relMSE ratio |",
             "|---|---:|---:|---|---:|---:|---:|"]
    for run in scenes:
        v = run.versus_mitsuba_relmse
        if v is None:
            continue
        lines.append(f"| {scene_cell(run)} | {run.reference_error:.4f} | {v.target:.3g} | {run.curves[v.other].label} | "
                     f"{reading_cell(v.other_seconds, '.2f')} | **{ratio_cell(v.speedup, v.other_seconds)}** | "
                     f"{ratio_cell(v.error_ratio, v.other_error)} |")
    return "\n".join(lines)


def relmse_summary(scenes: list[SceneRun]) -> str:
    readings = [run.versus_mitsuba_relmse for run in scenes if run.versus_mitsuba_relmse is not None]
    # A loop relMSE ≤ 0 is below what the reference's noise lets one read: no reading. Above it, an
    # infinite speed-up is a competitor that never gets that low: the loop ahead.
    speedups = [v.speedup for v in readings if v.target > 0 and not math.isnan(v.speedup)]
    if not speedups:
        return "No scene has a relMSE reading."
    ahead = sum(s > 1 for s in speedups)
    return (f"In relMSE less the references' noise the loop reaches the better `mi.render` + OIDN's error in less "
            f"wall time on **{ahead} of {len(speedups)}** scenes; median equal-error speed-up "
            f"**{statistics.median(speedups):.2f}×**.")


def curve_tables(scenes: list[SceneRun]) -> str:
    blocks = []
    for run in scenes:
        curves = list(run.curves.values())
        lines = [f"**{scene_cell(run)}**, reference's own relative error {run.reference_error:.4f}", "",
                 "| spp | " + " | ".join(c.label for c in curves) + " |", "|---:|" + "---:|" * len(curves)]
        for i in range(max(len(c.points) for c in curves)):
            cells = [f"{c.points[i].smape:.4g} / {c.points[i].relmse:.3g} @ {c.points[i].seconds:.2f} s"
                     if i < len(c.points) else "" for c in curves]
            lines.append(f"| {curves[0].points[i].spp:g} | " + " | ".join(cells) + " |")
        blocks.append("\n".join(lines))
    return "\n\n".join(blocks)


def stage_tables(scenes: list[SceneRun]) -> str:
    lines = ["| scene | iteration | spp | " + " | ".join(LOOP_STAGES) + " | total s |",
             "|---|---:|---:|" + "---:|" * len(LOOP_STAGES) + "---:|"]
    for run in scenes:
        for i, point in enumerate(run.curves[LOOP].points):
            lines.append(f"| {run.scene.name} | {i} | {point.spp:g} | "
                         + " | ".join(f"{point.stages.get(s, 0.0):.3f}" for s in LOOP_STAGES)
                         + f" | {sum(point.stages.values()):.2f} |")
    return "\n".join(lines)


def compile_table(scenes: list[SceneRun]) -> str:
    """Per scene, the seconds Dr.Jit spent compiling kernels in each method's untimed warm-up."""
    order = ("mitsuba", "mitsuba-box", LOOP, UNIFORM)
    lines = ["| scene | `mi.render` + OIDN, the scene's filter | `mi.render` + OIDN, box film | the loop (error allocator) | uniform + ours |",
             "|---|---:|---:|---:|---:|"]
    for run in scenes:
        cells = [f"{run.curves[k].compile_s:.2f}" if k in run.curves and math.isfinite(run.curves[k].compile_s) else ""
                 for k in order]
        lines.append(f"| {run.scene.name} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def memory_table(scenes: list[SceneRun]) -> str:
    order = ("mitsuba", "mitsuba-box", LOOP, UNIFORM)
    keys = [k for k in order if any(k in run.curves for run in scenes)]
    labels = {k: next(run.curves[k].label for run in scenes if k in run.curves) for k in keys}
    lines = ["| scene | " + " | ".join(f"{labels[k]}: peak / growth MB" for k in keys) + " |",
             "|---|" + "---:|" * len(keys)]
    for run in scenes:
        cells = [f"{run.curves[k].peak_rss_mb:.0f} / {run.curves[k].rss_growth_mb:.0f}" if k in run.curves else ""
                 for k in keys]
        lines.append(f"| {scene_cell(run)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def oidn_ms_per_mp(run: SceneRun) -> float:
    calls = [p.stages["oidn"] for c in run.curves.values() if c.key.startswith("mitsuba") for p in c.points]
    return 1000 * statistics.median(calls) / run.film.megapixels


def candidate_label(scenes: list[SceneRun]) -> str:
    """The OIDN-candidate row's label, read off the weights that ran (their config's
    `oidn_candidate`), so the row says whether its figure is an OIDN call or a 0 for none."""
    if any(run.costs.takes_candidate for run in scenes):
        return "OIDN candidate inside the denoiser (an OIDN call, quality high: these weights take one)"
    return "OIDN candidate inside the denoiser (0: these weights take none)"


def network_table(scenes: list[SceneRun], probe: CostProbe | None, threads: int) -> str:
    rows = [("denoiser (full pass, without its OIDN call)", lambda r: r.costs.per_megapixel("denoiser")),
            (candidate_label(scenes), lambda r: r.costs.per_megapixel("oidn_candidate")),
            ("error network", lambda r: r.costs.per_megapixel("error_network")),
            ("λ tail (from cached features)", lambda r: r.costs.per_megapixel("lambda_tail")),
            ("OIDN alone (`mi.render` + OIDN, quality high)", oidn_ms_per_mp)]
    lines = ["| network | median ms / MP | min | max |", "|---|---:|---:|---:|"]
    for label, value in rows:
        values = [value(run) for run in scenes]
        lines.append(f"| {label} | {statistics.median(values):.0f} | {min(values):.0f} | {max(values):.0f} |")
    ratios = [(run.costs.per_megapixel("denoiser") + run.costs.per_megapixel("oidn_candidate")) / oidn_ms_per_mp(run)
              for run in scenes]
    lines += ["", f"Our denoise (the full pass with its OIDN call) takes **{statistics.median(ratios):.2f}×** the time "
                  f"of OIDN alone on the same image (median; {min(ratios):.2f}–{max(ratios):.2f}×; bar on a GPU: "
                  "≤ 3×)."]
    if probe is not None:
        c = probe.costs
        lines += ["", f"At {c.megapixels:.2f} MP ({probe.scene}, `--costs-megapixels`): denoiser "
                      f"{c.per_megapixel('denoiser'):.0f}, its OIDN candidate (an OIDN call, quality high) "
                      f"{c.per_megapixel('oidn_candidate'):.0f}, error network {c.per_megapixel('error_network'):.0f}, "
                      f"λ tail {c.per_megapixel('lambda_tail'):.0f} ms / MP; **a λ edit's tail takes "
                      f"{c.ms['lambda_tail']:.0f} ms there** (bar ≤ 300 ms on 2 CPU threads, this run: "
                      f"{threads} thread(s): {'met' if c.ms['lambda_tail'] <= 300 else 'not met'})."]
    mp = statistics.median(run.film.megapixels for run in scenes)
    tails = [run.costs.ms["lambda_tail"] for run in scenes]
    scaled = (f"; scaled linearly to 2 MP: {statistics.median(tails) * 2.0 / mp:.0f} ms" if mp >= 0.5 else
              "; not scaled to 2 MP from so small a film, where per-call overhead dominates")
    lines += ["", f"λ tail per edit at this size (median {mp:.2f} MP): {statistics.median(tails):.0f} ms "
                  f"(bar at 2 MP: ≤ 300 ms on 2 CPU threads{scaled}). A λ edit's whole round trip over HTTP at "
                  "1920×1080, on both job backends of a real server, with its parts: docs/lambda-edit.md "
                  "(`renderloop bench --lambda-edit`)."]
    return "\n".join(lines)


def fixed_costs_rows(costs: list[FixedCosts]) -> list[str]:
    lines = ["| stage | fixed | median ms per call | median ms / MP | min–max ms / MP | share of iteration 0 (16 spp) "
             "| share of the last iteration |", "|---|---|---:|---:|---:|---:|---:|"]
    for key, label, fixed in COST_STAGES:
        ms = [c.ms[key] for c in costs]
        per_mp = [c.per_megapixel(key) for c in costs]
        first = [c.share(key, 0) for c in costs]
        last = [c.share(key, -1) for c in costs]
        lines.append(f"| {label} | {'yes' if fixed else 'no'} | {statistics.median(ms):.1f} | "
                     f"{statistics.median(per_mp):.0f} | {min(per_mp):.0f}–{max(per_mp):.0f} | "
                     f"{statistics.median(first):.1%} | {statistics.median(last):.1%} |")
    return lines


def probe_section(probe: CostProbe) -> list[str]:
    c = probe.costs
    return ["", f"**At {probe.film} ({c.megapixels:.2f} MP), {probe.scene}:** one 16-spp iteration of the loop (error "
                "allocator), no reference (`--costs-megapixels`); the same measurements. Peak RSS of the process "
                f"during that iteration: **{probe.peak_rss_mb / 1024:.2f} GB** (growth {probe.rss_growth_mb:.0f} MB); "
                f"the state snapshot on the loop's thread: {c.worker_ms:.0f} ms per iteration "
                f"({c.worker_ms / c.megapixels:.0f} ms / MP); the checkpoint + preview writes it feeds, on a "
                f"background thread: {c.background_ms:.0f} ms.", "", *fixed_costs_rows([c])]


def fixed_costs_table(scenes: list[SceneRun], probe: CostProbe | None = None) -> str:
    lines = [f"**At the benchmark's size** (medians over {len(scenes)} scene(s)):", "",
             *fixed_costs_rows([run.costs for run in scenes])]
    if probe is not None:
        lines += probe_section(probe)
    return "\n".join(lines)


def stall_note(scenes: list[SceneRun], probe: CostProbe | None = None) -> str:
    worker = [run.costs.worker_ms for run in scenes]
    share = [run.costs.stall_share for run in scenes]
    megapixels = statistics.median(r.costs.megapixels for r in scenes)
    at_probe = ""
    if probe is not None:
        c = probe.costs
        first = c.share("snapshot", 0)
        at_probe = (f" At {c.megapixels:.2f} MP the snapshot takes **{c.worker_ms:.0f} ms per iteration**, "
                    f"{first:.1%} of a 16-spp iteration there, and the writes it feeds {c.background_ms:.0f} ms "
                    f"(checkpoint {c.ms['checkpoint']:.0f} ms, previews {c.ms['preview']:.0f} ms) beside the next "
                    "render, which waits for them only if it ends first.")
    return (f"**What the writes cost the render:** the thread backend's worker copies the loop state on the loop's "
            f"thread (a median **{statistics.median(worker):.0f} ms per iteration** at the benchmark's size, "
            f"{statistics.median(worker) / megapixels:.0f} ms / MP, {statistics.median(share):.1%} of a whole job's "
            f"wall time, {min(share):.1%}–{max(share):.1%} over the scenes) and writes the checkpoint and the "
            "previews from that copy on a background thread (service/jobs/checkpoint_writer.py) while the next "
            f"iteration renders.{at_probe} The Ray backend's leader actor still writes its checkpoint on its own "
            "thread (service/jobs/ray_actor.py).")


def fixed_costs_note(scenes: list[SceneRun]) -> str:
    return ("Measured on each scene's finished loop (error allocator) at this size, by calling the functions the "
            "loop and the job worker call, median of 3 calls each; ms / MP divides by the film's megapixels. "
            "Shares: of that iteration's wall time (its four loop stages) plus the state snapshot the worker "
            "takes on the loop's thread; the render row's ms are the last iteration's, its shares each iteration's own. "
            "The final image is composed once an iteration, after the error network, and counted in its denoise "
            "stage (RenderLoop.finish_step); a λ edit pays only its blend. "
            "On the CPU the tensors live in host memory, so the two copy rows are layout copies; on a GPU "
            "they are the host/device transfers.")


def full_command(settings: Settings) -> str:
    if settings.megapixels >= FULL_MEGAPIXELS * 0.9 and settings.max_spp >= 1024:
        return f"This run is the full one (`{settings.command}`)."
    return (f"This run is **not** the full 2 MP one. The full figures (every scene of scenes/dev and scenes/val, "
            f"~2 MP, 16…1024 spp, 4096-spp references) come from `{FULL_COMMAND}` (hours on a 2-core CPU; the "
            "references alone are 8 G samples per scene).")


def report_text(results: Results) -> str:
    s, scenes = results.settings, results.scenes
    levels = sorted({p.spp for run in scenes for p in run.curves[LOOP].points})
    tiny = ("**A small run** (below ~1 MP): figures at this size do not carry over to 1080p. "
            if s.megapixels < 1 else "")
    return fill(
        "versus_mitsuba.md",
        provenance=provenance(s.command, active_variant()), load_before=results.load_before,
        load_after=load_average(), minutes=f"{results.seconds / 60:.1f}", weights=results.nets.description,
        oidn_status=results.oidn_status, tiny=tiny, size_label=f"~{s.megapixels:g} MP",
        suites=("scenes/dev and scenes/val" if not s.subset else
                f"scenes/dev and scenes/val named by `--scenes` ({', '.join(s.subset)})"),
        megapixels=f"{s.megapixels:g}", levels=", ".join(f"{x:g}" for x in levels), threads=s.threads,
        aovs=AOVS, max_lanes=f"{COMPETITOR_CALL_LANES:,}", iterations=len(levels), reference_spp=s.reference_spp,
        max_spp=s.max_spp, extrapolation_limit=f"{EXTRAPOLATION_LIMIT:g}",
        headline_table=headline_table(scenes), summary=summary(scenes, s.megapixels),
        end_table=end_table(scenes), end_summary=end_summary(scenes),
        relmse_table=relmse_table(scenes), relmse_summary=relmse_summary(scenes),
        curve_tables=curve_tables(scenes), stage_tables=stage_tables(scenes), compile_table=compile_table(scenes), memory_table=memory_table(scenes),
        network_table=network_table(scenes, results.probe, s.threads), fixed_costs_note=fixed_costs_note(scenes),
        fixed_costs_table=fixed_costs_table(scenes, results.probe), stall_note=stall_note(scenes, results.probe),
        full_command=full_command(s),
    )
