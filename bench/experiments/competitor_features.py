"""What the `mi.render` + OIDN competitor paid for its albedo and normals, and how the published
~2 MP speed-ups read once it pays only what they cost.

The 2 MP reports (the `--versus-mitsuba` reports in docs/) rendered the competitor with Mitsuba's
recipe for OIDN's features: an `aov` integrator wrapping the scene's own. Its images are those of
two renders at the same seed, the colour with the scene's integrator and the features with an `aov`
integrator alone (tests/bench/test_versus_mitsuba.py), which is what the benchmark renders now
(bench/versus_mitsuba_scene.render_with_aovs). So the reports' errors stand and only the
competitor's times change. For each scene of the suite's newest CPU reading, at that report's film
size and for each competitor film it ran (the scene's filter, box): the seconds of one wrapped render,
a plain render and a features render at SPP (the median of interleaved repeats, each kind compiled
by an untimed call first), and of an OIDN call; then the report's printed curves re-read with each
competitor point's render time scaled by (plain + features) ÷ wrapped and its OIDN time kept,
through the same readings as the suite page (bench.versus_mitsuba_run.better_of,
least_at_competitor_ends).

    python -m bench.experiments.competitor_features [--spp 2] [--repeats 3] [--scenes A,B] [--reports docs]
                                                    [--costs-from FILE] [-o FILE]

`--costs-from` takes the costs from an earlier run's report instead of rendering (after a new
`--versus-mitsuba` run: its scenes, timed apart already, are shown as they are).
"""
from __future__ import annotations

import argparse
import math
import re
import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np

from bench.common import experiment_command, oidn_denoiser, provenance, publish
from bench.dev_references import DevScene
from bench.versus_mitsuba import suite_scenes
from bench.versus_mitsuba_report import LOOP_LABEL
from bench.versus_mitsuba_run import MITSUBA_SEED, Curve, CurvePoint, better_of, least_at_competitor_ends
from bench.versus_mitsuba_scene import AOV_CHANNELS, AOVS, Film, competitor_scene, feature_integrator
from bench.versus_mitsuba_suite import Reading, cpu_standing, printed_curves, suite_names
from service.render.runtime import mitsuba

BOX_LABEL = "box film"   # what a competitor curve's key says when its film was switched to `box`


@dataclass(frozen=True)
class FeatureCost:
    """Seconds of one render of each kind, and of one OIDN call, for one competitor film."""

    wrapped: float    # `aov` wrapping the scene's integrator: colour and features in one render
    plain: float      # the scene's integrator alone
    features: float   # `aov` alone
    oidn: float

    @property
    def ratio(self) -> float:
        """The competitor's render time now ÷ before: (plain + features) ÷ wrapped."""
        return (self.plain + self.features) / self.wrapped


def _seconds(call) -> float:
    started = time.perf_counter()
    call()
    return time.perf_counter() - started


def feature_cost(scene: DevScene, film: Film, box: bool, spp: int, repeats: int = 3) -> FeatureCost:
    """The median of `repeats` timed renders of each kind at `spp` (after an untimed one that
    compiles its kernels), the kinds interleaved so that a busy moment of a shared host lands on
    one repeat, not on one kind; and the median of as many timed OIDN calls."""
    mi = mitsuba()
    loaded = competitor_scene(scene, film, box)
    wrapped = mi.load_dict({"type": "aov", "aovs": AOVS, "img": loaded.integrator()})
    features = feature_integrator()
    calls = {"wrapped": lambda: mi.render(loaded, integrator=wrapped, spp=spp, seed=MITSUBA_SEED),
             "plain": lambda: mi.render(loaded, spp=spp, seed=MITSUBA_SEED),
             "features": lambda: mi.render(loaded, integrator=features, spp=spp, seed=MITSUBA_SEED)}
    images = {name: np.asarray(call()) for name, call in calls.items()}   # compiles, untimed
    seconds: dict[str, list[float]] = {name: [] for name in calls}
    for _ in range(repeats):
        for name, call in calls.items():
            seconds[name].append(_seconds(lambda call=call: np.asarray(call())))
    oidn, _ = oidn_denoiser()
    color, aovs = images["plain"][..., :3], images["features"]
    arguments = (color, aovs[..., -AOV_CHANNELS:-3], aovs[..., -3:])
    oidn(*arguments)
    oidn_seconds = statistics.median(_seconds(lambda: oidn(*arguments)) for _ in range(repeats))
    return FeatureCost(*(statistics.median(seconds[name]) for name in calls), oidn_seconds)


def retimed(curve: Curve, cost: FeatureCost) -> Curve:
    """`curve` with each point's render time scaled by cost.ratio, its OIDN call's kept."""
    points = [CurvePoint(p.spp, max(p.seconds - cost.oidn, 0.0) * cost.ratio + cost.oidn, p.smape, p.stages, p.relmse)
              for p in curve.points]
    return Curve(curve.key, curve.label, points)


@dataclass
class SceneReread:
    reading: Reading
    costs: dict[str, FeatureCost]          # competitor curve key → its cost
    before: tuple[float, str]              # (equal-error speed-up in SMAPE, how read) from the printed curves
    after: tuple[float, str]
    relmse_before: tuple[float, str]       # the same in relMSE (the references' noise taken out)
    relmse_after: tuple[float, str]
    end_before: float                      # SMAPE, at the competitors' last points (least favourable)
    end_after: float
    end_measured: bool


def competitor_keys(reading: Reading, report: Path) -> tuple[Curve, list[Curve]]:
    """The loop's printed curve and the competitors' for one scene of `report`."""
    curves = {c.key: c for c in printed_curves(report.read_text().splitlines(), f"{reading.scene} ({reading.film})")}
    competitors = [c for key, c in curves.items() if key.startswith("`mi.render`")]
    if LOOP_LABEL not in curves or not competitors:
        raise ValueError(f"{report.name}: no printed curves for {reading.scene}")
    return curves[LOOP_LABEL], competitors


def suite_curves(reading: Reading, report: Path, costs: dict[str, dict[str, FeatureCost]]) -> tuple[Curve, list[Curve]]:
    """The loop's printed curve and the competitors' as the suite re-read times them: a competitor that
    wrapped its features re-timed by the scene's `costs` (costs_from_report)."""
    loop, competitors = competitor_keys(reading, report)
    if not reading.features_apart:
        competitors = [retimed(c, costs[reading.scene][film_kind(c.key)]) for c in competitors]
    return loop, competitors


def measured_costs(reading: Reading, competitors: list[Curve], spp: int, repeats: int) -> dict[str, FeatureCost]:
    width, height = (int(v) for v in re.match(r"(\d+)×(\d+)", reading.film).groups())
    (scene,) = suite_scenes([reading.scene])
    return {c.key: feature_cost(scene, Film(width, height), BOX_LABEL in c.key, spp, repeats) for c in competitors}


class SuiteReadings(NamedTuple):
    """One scene's loop curve against its competitors, read as the suite page reads them
    (bench.versus_mitsuba_run.better_of, least_at_competitor_ends)."""
    smape: tuple[float, str]    # equal-error speed-up in SMAPE over the better competitor, how read
    relmse: tuple[float, str]   # the same in relMSE (the references' noise taken out)
    end: float                  # SMAPE speed-up at the competitors' last points (least favourable)
    end_measured: bool


def suite_readings(loop: Curve, competitors: list[Curve]) -> SuiteReadings:
    smape, relmse = better_of(loop, competitors, "smape"), better_of(loop, competitors, "relmse")
    end = least_at_competitor_ends(loop, competitors)
    return SuiteReadings((smape.speedup, smape.other_seconds.how), (relmse.speedup, relmse.other_seconds.how),
                         end.speedup, end.measured)


def reread(reading: Reading, loop: Curve, competitors: list[Curve], costs: dict[str, FeatureCost]) -> SceneReread:
    """One scene's printed curves read as printed and with the competitors re-timed; a reading whose
    competitor already rendered its features apart (no `costs`) reads the same both ways."""
    after = [retimed(c, costs[c.key]) for c in competitors] if costs else competitors
    old, new = suite_readings(loop, competitors), suite_readings(loop, after)
    return SceneReread(reading, costs, old.smape, new.smape, old.relmse, new.relmse, old.end, new.end,
                       new.end_measured)


COSTS_HEADER = "| scene (film) | report | wrapped s |"
TIMED_APART = "timed apart"   # the ratio cell of a reading whose competitor rendered its features apart


def measured_timings(spp: int, repeats: int) -> str:
    return (f"the median of {repeats} renders of each kind at {spp} spp per competitor film, interleaved, after "
            "an untimed one; and of as many OIDN calls.")


def source_timings(path: Path) -> str:
    """How the costs in an earlier run's report were measured: its command, date and commit, or the
    run it took them from in turn."""
    text = path.read_text()
    timings = re.search(r"^Timings: (.*?) (?:A reading whose competitor|Speed-ups:)", text, re.M | re.S).group(1)
    if timings.startswith("from `"):
        return timings
    command = re.search(r"^Command: `([^`]+)`", text, re.M).group(1)
    stamp = re.search(r"^Date: (\S+); commit (\w+)", text, re.M)
    return f"from `{command}` ({stamp.group(1)}, commit {stamp.group(2)}): {timings}"


def costs_from_report(path: Path) -> dict[str, dict[str, FeatureCost]]:
    """scene → {"own" or "box" → cost} from the table of an earlier run of this command (its -o file)."""
    costs: dict[str, dict[str, FeatureCost]] = {}
    scene = None
    lines = path.read_text().splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(COSTS_HEADER))
    for line in lines[start + 2:]:
        if not line.startswith("|"):
            break
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        if cells[6] == TIMED_APART:
            continue
        label = re.fullmatch(r"(?:(\w+) \(.*\) )?\[(own|box)\]", cells[0])
        scene = label.group(1) or scene
        costs.setdefault(scene, {})[label.group(2)] = FeatureCost(*(float(v) for v in cells[2:6]))
    return costs


def film_kind(key: str) -> str:
    return "box" if BOX_LABEL in key else "own"


def speedup_text(value: float, how: str) -> str:
    if math.isnan(value):
        return "n/a"
    if not math.isfinite(value):
        return "never"
    return f"{'~' if how == 'extrapolated' else ''}{value:.2f}×"


def count_and_median(values: list[float]) -> str:
    readable = [v for v in values if not math.isnan(v)]
    return f"ahead on {sum(v > 1 for v in readable)} of {len(readable)}, median {statistics.median(readable):.2f}×"


def readings_summary(first: str, second: str, smape: tuple[list[float], list[float]],
                     relmse: tuple[list[float], list[float]], end: tuple[list[float], list[float]]) -> str:
    """The suite's three readings, each counted and its median taken under two timings of the loop
    or the competitor (`first`, and `second` in bold): SMAPE, relMSE, SMAPE at the competitors' last points."""
    def pair(values: tuple[list[float], list[float]]) -> str:
        return f"{first} {count_and_median(values[0])}; {second} **{count_and_median(values[1])}**"
    return f"SMAPE: {pair(smape)}. relMSE: {pair(relmse)}. At the competitors' last points (SMAPE): {pair(end)}."


def report_text(rows: list[SceneReread], command: str, timings: str) -> str:
    lines = ["# The `mi.render` + OIDN competitor's features: what they cost, and the 2 MP suite re-read", "",
             provenance(command), "", " ".join(__doc__.split("\n\n")[1].split()), "",
             f"Timings: {timings} A reading whose competitor already rendered its features apart reads "
             f"\"{TIMED_APART}\" and is not re-timed. Speed-ups: "
             "the loop's equal-error speed-up over the better competitor at the loop's final error (SMAPE, and "
             "relMSE with the references' noise taken out; `~`: read off the competitor's fitted power law), and "
             "in SMAPE at the competitors' own last points (no extrapolation of the competitor; `~`: of the loop). "
             "All are read off the reports' printed curves; a report that printed SMAPE to 4 decimals gives a scene "
             "below 0.01 few significant digits (point_object's 0.0005–0.0008: one), so its reading is rough, and a "
             "run that times the competitor apart replaces it.",
             "", COSTS_HEADER + " plain s | features s | OIDN s | ratio | SMAPE speed-up as printed | re-timed "
             "| relMSE speed-up as printed | re-timed | at the competitor's last point, as printed | re-timed |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for row in rows:
        if not row.costs:
            lines.append(f"| {row.reading.scene} ({row.reading.film}) | {row.reading.report} | | | | | {TIMED_APART} | "
                         + " | ".join([speedup_text(*row.before), speedup_text(*row.after),
                                       speedup_text(*row.relmse_before), speedup_text(*row.relmse_after),
                                       f"{row.end_before:.2f}×", f"{row.end_after:.2f}×"])
                         + " |")
        for index, (key, cost) in enumerate(row.costs.items()):
            label = f"{row.reading.scene} ({row.reading.film}) " if index == 0 else ""
            cells = [f"{label}[{film_kind(key)}]", row.reading.report if index == 0 else "", f"{cost.wrapped:.3f}",
                     f"{cost.plain:.3f}", f"{cost.features:.3f}", f"{cost.oidn:.3f}", f"{cost.ratio:.3f}"]
            cells += ([speedup_text(*row.before), speedup_text(*row.after), speedup_text(*row.relmse_before),
                       speedup_text(*row.relmse_after), f"{row.end_before:.2f}×",
                       f"{'' if row.end_measured else '~'}{row.end_after:.2f}×"] if index == 0 else [""] * 6)
            lines.append("| " + " | ".join(cells) + " |")
    ratios = [cost.ratio for row in rows for cost in row.costs.values()]
    lines += ["", f"Competitor render time ratio (plain + features ÷ wrapped): median {statistics.median(ratios):.3f} "
              f"({min(ratios):.3f}–{max(ratios):.3f}) over {len(ratios)} films.", "",
              f"Over {len(rows)} scenes (as printed: each report's own timing, the wrapped competitor's where it "
              f"rendered so; re-timed: every competitor's features apart), "
              + readings_summary("as printed", "re-timed", ([r.before[0] for r in rows], [r.after[0] for r in rows]),
                                 ([r.relmse_before[0] for r in rows], [r.relmse_after[0] for r in rows]),
                                 ([r.end_before for r in rows], [r.end_after for r in rows]))]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--spp", type=int, default=2, help="samples per pixel of each timed render")
    parser.add_argument("--repeats", type=int, default=3, help="timed renders of each kind (their median)")
    parser.add_argument("--scenes", type=lambda text: text.split(","), default=None)
    parser.add_argument("--reports", type=Path, default=Path("docs"))
    parser.add_argument("--costs-from", type=Path, default=None,
                        help="take the costs from an earlier run's report (its -o file) instead of rendering")
    parser.add_argument("-o", "--out", type=Path, default=None, help="write the report here too")
    args = parser.parse_args(argv)
    standing = cpu_standing(args.reports)
    earlier = costs_from_report(args.costs_from) if args.costs_from else None
    rows = []
    for name in args.scenes or suite_names():
        reading = standing.newest.get(name)
        if reading is None:
            print(f"{name}: no CPU reading", flush=True)
            continue
        loop, competitors = competitor_keys(reading, args.reports / reading.report)
        if reading.features_apart:
            costs = {}
        elif earlier is not None:
            costs = {c.key: earlier[name][film_kind(c.key)] for c in competitors}
        else:
            costs = measured_costs(reading, competitors, args.spp, args.repeats)
        row = reread(reading, loop, competitors, costs)
        rows.append(row)
        ratios = ", ".join(f"{cost.ratio:.3f}" for cost in row.costs.values()) or TIMED_APART
        print(f"{name}: ratio {ratios}; SMAPE speed-up {speedup_text(*row.before)} -> {speedup_text(*row.after)}; "
              f"relMSE {speedup_text(*row.relmse_before)} -> {speedup_text(*row.relmse_after)}; at the competitor's "
              f"last point {row.end_before:.2f}x -> {row.end_after:.2f}x", flush=True)
    command = experiment_command("bench.experiments.competitor_features", argv)
    timings = source_timings(args.costs_from) if args.costs_from else measured_timings(args.spp, args.repeats)
    text = report_text(rows, command, timings)
    publish(text, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
