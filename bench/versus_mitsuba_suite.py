"""`renderloop bench --versus-mitsuba-suite`: the suite's standing against `mi.render` + OIDN at ~2 MP,
read from the `--versus-mitsuba` reports already written (benchmarks-versus-mitsuba*.md in docs/).

A 2 MP run of one scene takes 25–40 min on the 2-core CPU, so the suite's 21 scenes are measured
over several runs, each writing a report of its own. This module reads their headline tables
(SMAPE and relMSE), keeps each scene's newest reading per Mitsuba variant, and measures the
issue's bars against the *whole* suite: a scene not yet measured counts as not ahead, so the
share of the suite the loop wins on cannot be read as met from a subset.
"""
from __future__ import annotations

import argparse
import math
import re
import statistics
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path

from bench.common import command_line
from bench.loop_run import EXTRAPOLATION_LIMIT
from bench.versus_mitsuba import DEFAULT_MAX_SPP, DEFAULT_REFERENCE_SPP, suite_scenes
from bench.versus_mitsuba_report import END_HEADER, LOOP_LABEL, end_cells
from bench.versus_mitsuba_run import Curve, CurvePoint, least_at_competitor_ends
from bench.versus_mitsuba_scene import scene_sampler
from service.render.scenes import STRATIFYING_SAMPLER_PLUGINS

SUMMARY_NAME = "benchmarks-versus-mitsuba-suite.md"
REPORT_GLOB = "benchmarks-versus-mitsuba*.md"
SMAPE_HEADER = "| scene (film, filter) | loop SMAPE |"
RELMSE_HEADER = "| scene (film, filter) | reference's relative error | loop relMSE |"
# The bars (43): the loop ahead on ≥ 75 % of the suite, median equal-error speed-up ≥ 1.5×
# (goal 2×), peak RSS ≤ 8 GB for a 2 MP job.
SHARE_BAR, MEDIAN_BAR, MEDIAN_GOAL, RSS_BAR_GB = 0.75, 1.5, 2.0, 8.0
VARIANT_LABELS = {"llvm_ad_rgb": "CPU (`llvm_ad_rgb`)", "cuda_ad_rgb": "GPU (`cuda_ad_rgb`)"}
# What a report says when its references were rendered with the `independent` sampler in place of
# the scene's own, and when `mi.render` rendered each level in as few calls as the sampler allows
# (bench/templates/versus_mitsuba.md). Over 16 samples Mitsuba's `stratified` sampler is biased:
# reports without the first rendered a stratifying scene's reference with it in 16-spp calls;
# reports without the second split the competitor's levels into 16-spp calls at 2 MP, which
# handicaps it (bench.experiments.competitor_calls, docs/decisions.md).
INDEPENDENT_REFERENCE_MARK = "the scene's sampler replaced by `independent`"
FEW_CALLS_MARK = "in as few calls as the sampler allows"
# What a report says when `mi.render` + OIDN rendered its albedo and normals apart from the colour.
# Reports without it timed an `aov` integrator wrapping the scene's, the same images for about twice
# the render time (bench.experiments.competitor_features, docs/competitor-features.md).
FEATURES_APART_MARK = "a second render of the same samples with an `aov` integrator alone"


@dataclass(frozen=True)
class Reading:
    """One scene's headline figures in one report."""
    scene: str
    film: str                 # "1633×1225, gaussian"
    loop_smape: float         # the loop's final SMAPE
    speedup: float            # equal-error speed-up in SMAPE (> 1: the loop ahead)
    extrapolated: bool        # read off a fitted power law, not between measured points
    equal_time: str           # the equal-time SMAPE ratio as printed
    relmse_speedup: float     # the equal-error speed-up in relMSE (nan where unreadable, inf: see FLAT_MARK)
    reference_error: float    # the reference's own mean relative standard error: SMAPE's floor
    peak_rss_mb: float
    report: str               # the report's file name
    commit: str
    date: str                 # ISO, as the report prints it: newer sorts later
    settings: str             # "16–128 spp, 1024-spp references": runs may differ
    # the reference took the `independent` sampler and `mi.render` rendered each level in as few
    # calls as the sampler allows (or the scene's sampler does not stratify)
    fair_to_stratifying: bool = True
    # the speed-up at the competitors' own last points, as printed ("≥1.52×", "2.47×", "~0.9×"), or
    # recomputed from the printed curves of a report from before that table ("2.47× ‡"); empty
    # where neither can be read
    end_speedup: str = ""
    relmse_extrapolated: bool = False  # the relMSE speed-up read off a power law (`~`)
    # `mi.render` + OIDN rendered its features apart (FEATURES_APART_MARK), not in a wrapping `aov`
    features_apart: bool = True


@dataclass
class VariantStanding:
    """The suite's standing for one Mitsuba variant: the newest reading per scene."""
    variant: str
    suite: list[str]
    newest: dict[str, Reading] = field(default_factory=dict)
    older: dict[str, list[Reading]] = field(default_factory=dict)

    @property
    def ahead(self) -> list[Reading]:
        return [r for r in self.newest.values() if r.speedup > 1.0]

    @property
    def ahead_in_relmse(self) -> list[Reading]:
        return [r for r in self.newest.values() if r.relmse_speedup > 1.0]

    @property
    def equal_time_measured(self) -> list[float]:
        """The equal-time SMAPE ratios read inside the competitor's measured curve (not `~`): the
        loop's final time falls between two of the competitor's points, so no power law is involved."""
        ratios = []
        for r in self.newest.values():
            try:
                ratio, extrapolated = _number(r.equal_time)
            except ValueError:
                continue
            if not extrapolated:
                ratios.append(ratio)
        return ratios

    @property
    def end_speedups_measured(self) -> list[float]:
        """The speed-ups at the competitors' own last points that need no extrapolation (unmarked,
        or `≥`: a lower bound from the loop's first point)."""
        values = []
        for r in self.newest.values():
            text = r.end_speedup.removesuffix(FROM_PRINTED_CURVES).lstrip("≥")
            if text and not text.startswith("~"):
                values.append(_number(text)[0])
        return values

    @property
    def unfair_to_stratifying(self) -> list[Reading]:
        return [r for r in self.newest.values() if not r.fair_to_stratifying]

    @property
    def wrapped_features(self) -> list[Reading]:
        return [r for r in self.newest.values() if not r.features_apart]

    @property
    def unmeasured(self) -> list[str]:
        return [name for name in self.suite if name not in self.newest]

    @property
    def median_speedup(self) -> float:
        return statistics.median(r.speedup for r in self.newest.values())


def _cells(line: str) -> list[str]:
    return [cell.strip() for cell in line.strip().strip("|").split("|")]


def _number(text: str) -> tuple[float, bool]:
    """A printed figure such as `**~5.27×**` → (5.27, extrapolated); a bound's `≤`/`≥` is dropped."""
    plain = text.replace("*", "").replace("×", "").strip()
    return float(plain.lstrip("~≤≥")), plain.startswith("~")


def table_rows(lines: list[str], header: str) -> list[list[str]]:
    """The body rows of the first table whose header line starts with `header`."""
    for i, line in enumerate(lines):
        if line.startswith(header):
            rows = []
            for body in lines[i + 2:]:  # past the header and its |---| rule
                if not body.startswith("|"):
                    break
                rows.append(_cells(body))
            return rows
    return []


def _run_settings(text: str) -> str:
    """The sample range and reference spp of a report's command (the command's defaults where unset)."""
    command = re.search(r"^Command: `([^`]+)`", text, re.M)
    flags = command.group(1) if command else ""
    max_spp = re.search(r"--max-spp (\d+)", flags)
    reference_spp = re.search(r"--reference-spp (\d+)", flags)
    return (f"16–{max_spp.group(1) if max_spp else DEFAULT_MAX_SPP} spp, "
            f"{reference_spp.group(1) if reference_spp else DEFAULT_REFERENCE_SPP}-spp references")


# A cell of a report's per-scene curve table: "0.0160 / 5.22e-05 @ 101.95 s" (SMAPE / relMSE @ seconds).
CURVE_CELL = re.compile(r"([0-9.e+-]+) / (\S+) @ ([0-9.]+) s")
# Marks a speed-up that cannot be read because the competitor never gets as low as the loop: its
# curve does not fall, or so slowly that its power law would need more than EXTRAPOLATION_LIMIT
# times its last measured time (a report may print that guess, ~10⁹×: no estimate). Counted as the
# loop ahead; the speed-up at the competitor's last point, measured, carries the figure.
FLAT_MARK = " §"
# Marks a speed-up at the competitor's last point recomputed from a report's printed curve table
# (a report from before that reading; its SMAPE printed to 4 decimals, so the figure is approximate).
FROM_PRINTED_CURVES = " ‡"


def printed_curves(lines: list[str], label: str) -> list[Curve]:
    """The curves of the per-scene table headed by `**{label}**` (SMAPE, relMSE where printed, seconds)."""
    start = next((i for i, line in enumerate(lines) if line.startswith(f"**{label}**")), None)
    if start is None or start + 2 >= len(lines) or not lines[start + 2].startswith("| spp |"):
        return []
    names = _cells(lines[start + 2])[1:]
    points: dict[str, list[CurvePoint]] = {name: [] for name in names}
    for line in lines[start + 4:]:
        if not line.startswith("|"):
            break
        cells = _cells(line)
        for name, cell in zip(names, cells[1:]):
            match = CURVE_CELL.match(cell)
            if match:
                try:
                    relmse = float(match.group(2))
                except ValueError:   # an older report's relMSE column or an unreadable one
                    relmse = math.nan
                points[name].append(CurvePoint(float(cells[0]), float(match.group(3)), float(match.group(1)), {},
                                               relmse))
    return [Curve(name, name, pts) for name, pts in points.items() if pts]


def _end_from_printed_curves(lines: list[str], label: str) -> str:
    """The speed-up at the competitors' last points (`least_at_competitor_ends`) recomputed from a
    report's curve table, marked FROM_PRINTED_CURVES; empty where the table cannot be read."""
    curves = {c.key: c for c in printed_curves(lines, label)}
    competitors = [c for key, c in curves.items() if key.startswith("`mi.render`")]
    if LOOP_LABEL not in curves or not competitors:
        return ""
    _, speedup = end_cells(least_at_competitor_ends(curves[LOOP_LABEL], competitors))
    return speedup + FROM_PRINTED_CURVES


def _competitor_last_seconds(lines: list[str], scene: str, label: str) -> float | None:
    """The last measured time of the competitor `label` in the scene's printed curve table."""
    curve = next((c for c in printed_curves(lines, scene) if c.key == label), None)
    return max(p.seconds for p in curve.points) if curve else None


def _headline_speedup(lines: list[str], row: list[str], loop_error: float) -> tuple[float, bool]:
    """(speed-up, extrapolated) of a row of a headline table, SMAPE or relMSE (the competitor's label,
    its seconds to the loop's error and the speed-up in cells 3–5): inf where the competitor never
    gets that low (FLAT_MARK), nan where the loop's error is ≤ 0 (below the reference's noise)."""
    if row[4] == "never":
        return (math.inf, True) if loop_error > 0 else (math.nan, False)
    speedup, extrapolated = _number(row[5])
    if extrapolated:
        last = _competitor_last_seconds(lines, row[0], row[3])
        if last is not None and _number(row[4])[0] > EXTRAPOLATION_LIMIT * last:
            return math.inf, True
    return speedup, extrapolated


def parse_report(path: Path) -> tuple[str, list[Reading]]:
    """(Mitsuba variant, the headline readings) of one `--versus-mitsuba` report."""
    text = Path(path).read_text()
    lines = text.splitlines()
    variant = re.search(r"^Mitsuba variant: `([^`]+)`", text, re.M)
    stamp = re.search(r"^Date: (\S+); commit (\w+)", text, re.M)
    if variant is None or stamp is None:
        raise ValueError(f"{path}: not a --versus-mitsuba report (no 'Mitsuba variant' or 'Date' line)")
    settings = _run_settings(text)
    flat = " ".join(text.split())
    fair_to_stratifying = INDEPENDENT_REFERENCE_MARK in flat and FEW_CALLS_MARK in flat
    features_apart = FEATURES_APART_MARK in flat
    relmse = {row[0]: (_headline_speedup(lines, row, float(row[2])), float(row[1]))
              for row in table_rows(lines, RELMSE_HEADER)}
    at_end = {row[0]: row[5].replace("*", "") for row in table_rows(lines, END_HEADER)}
    readings = []
    for row in table_rows(lines, SMAPE_HEADER):
        label = re.fullmatch(r"(\w+) \((.+)\)", row[0])
        if label is None:
            raise ValueError(f"{path}: unreadable scene cell {row[0]!r}")
        speedup, extrapolated = _headline_speedup(lines, row, float(row[1]))
        (relmse_speedup, relmse_extrapolated), reference_error = relmse.get(row[0], ((math.nan, False), math.nan))
        readings.append(Reading(scene=label.group(1), film=label.group(2), loop_smape=float(row[1]), speedup=speedup,
                                extrapolated=extrapolated, equal_time=row[6],
                                relmse_speedup=relmse_speedup, relmse_extrapolated=relmse_extrapolated,
                                reference_error=reference_error, peak_rss_mb=float(row[8]),
                                report=Path(path).name, commit=stamp.group(2), date=stamp.group(1),
                                settings=settings, fair_to_stratifying=fair_to_stratifying,
                                features_apart=features_apart,
                                end_speedup=at_end.get(row[0]) or _end_from_printed_curves(lines, row[0])))
    return variant.group(1), readings


def suite_names() -> list[str]:
    """scenes/dev then scenes/val, as `--versus-mitsuba` runs them with no --scenes."""
    return [scene.name for scene in suite_scenes(None)]


def stratifying_scenes() -> set[str]:
    """The suite's scenes whose sampler stratifies: their references differ by sampler across runs."""
    return {scene.name for scene in suite_scenes(None) if scene_sampler(scene) in STRATIFYING_SAMPLER_PLUGINS}


def suite_standing(reports: list[Path], suite: list[str], stratifying: set[str] = frozenset()) -> list[VariantStanding]:
    """Each variant's standing over `reports`, CPU first; a scene's newest reading wins, the
    others are kept to show how far runs of one scene disagree. A reading of a `stratifying` scene
    from a report that kept the scene's sampler for its references or split `mi.render`'s levels
    into 16-spp calls is marked (Reading.fair_to_stratifying)."""
    by_variant: dict[str, list[Reading]] = {}
    for path in reports:
        variant, readings = parse_report(path)
        by_variant.setdefault(variant, []).extend(
            replace(r, fair_to_stratifying=r.fair_to_stratifying or r.scene not in stratifying) for r in readings)
    order = sorted(by_variant, key=lambda v: (v != "llvm_ad_rgb", v))
    standings = []
    for variant in order:
        standing = VariantStanding(variant, suite)
        for reading in sorted(by_variant[variant], key=lambda r: r.date):
            previous = standing.newest.get(reading.scene)
            if previous is not None:
                standing.older.setdefault(reading.scene, []).append(previous)
            standing.newest[reading.scene] = reading
        standings.append(standing)
    return standings


def _speedup_cell(speedup: float, extrapolated: bool) -> str:
    if math.isnan(speedup):
        return "n/a"
    if math.isinf(speedup):
        return "n/a" + FLAT_MARK
    return f"{'~' if extrapolated else ''}{speedup:.2f}×"


WRAPPED_MARK = " ¶"


def _speedup_text(r: Reading) -> str:
    return (_speedup_cell(r.speedup, r.extrapolated) + ("" if r.fair_to_stratifying else " †")
            + ("" if r.features_apart else WRAPPED_MARK))


def _equal_time_sentence(standing: VariantStanding) -> str:
    """The readings that need no extrapolation: at the loop's own wall time, inside the competitor's
    measured curve. A ratio printed as 1.00× counts as not ahead."""
    ratios = standing.equal_time_measured
    if not ratios:
        return ""
    ahead = sum(ratio < 1.0 for ratio in ratios)
    return (f" Read inside the competitor's measured curve with no extrapolation (the equal-time SMAPE ratio, "
            f"measured on {len(ratios)} of {len(standing.newest)}): the loop's SMAPE is lower on **{ahead} of "
            f"{len(ratios)}**, median {statistics.median(ratios):.2f}×.")


def _end_sentence(standing: VariantStanding) -> str:
    speedups = standing.end_speedups_measured
    if not speedups:
        return ""
    recomputed = sum(r.end_speedup.endswith(FROM_PRINTED_CURVES) for r in standing.newest.values()
                     if not r.end_speedup.startswith("~"))
    return (f" At the competitor's own last measured point, with no extrapolation at all ({len(speedups)} of "
            f"{len(standing.newest)} readings, {recomputed} of them recomputed from an older report's printed "
            f"curves, ‡): the loop gets there sooner on **{sum(s > 1 for s in speedups)} of {len(speedups)}**, "
            f"median {statistics.median(speedups):.2f}×.")


def _verdict(standing: VariantStanding) -> str:
    measured, total = len(standing.newest), len(standing.suite)
    ahead = len(standing.ahead)
    share = ahead / total if total else 0.0
    peak = max(r.peak_rss_mb for r in standing.newest.values()) / 1000.0
    share_word = "met" if share >= SHARE_BAR else ("not met" if ahead + len(standing.unmeasured) < SHARE_BAR * total
                                                    else "not yet (scenes unmeasured)")
    if standing.wrapped_features and share >= SHARE_BAR:
        share_word += " as timed, not once the competitor is re-timed (¶, below)"
    extrapolated = sum(r.extrapolated for r in standing.newest.values())
    return (f"Measured **{measured} of the suite's {total}** scenes. The loop reaches the better `mi.render` + "
            f"OIDN's error sooner on **{ahead} of {measured}** measured, {ahead} of {total} of the suite "
            f"({100 * share:.0f} %; bar ≥ {100 * SHARE_BAR:.0f} % of the suite: {share_word}). Median "
            f"equal-error speed-up over the measured scenes **{standing.median_speedup:.2f}×** (bar ≥ "
            f"{MEDIAN_BAR}×, goal {MEDIAN_GOAL}×; {extrapolated} of {measured} readings extrapolated). Peak RSS "
            f"**{peak:.2f} GB** at most (bar ≤ {RSS_BAR_GB:.0f} GB). In relMSE with the references' noise taken out: "
            f"ahead on **{len(standing.ahead_in_relmse)} of {measured}** measured." + _equal_time_sentence(standing)
            + _end_sentence(standing)
            + (f" {len(standing.unfair_to_stratifying)} of the {measured} readings (†) rest on a stratifying "
               "sampler's 16-spp bias: re-measure them." if standing.unfair_to_stratifying else "")
            + (f" **{len(standing.wrapped_features)} of the {measured} readings (¶) timed `mi.render` + OIDN with an "
               "`aov` integrator wrapped around the scene's, about twice the render time its images need**: "
               "`python -m bench.experiments.competitor_features` re-reads them with the competitor re-timed "
               "(docs/competitor-features.md)." if standing.wrapped_features else ""))


def summary_text(standings: list[VariantStanding], reports: list[Path], command: str) -> str:
    out = ["# The suite against `mi.render` + OIDN at ~2 MP, over every run", "",
           f"Command: `{command}`  ",
           f"Read from: {', '.join(f'[{p.name}]({p.name})' for p in sorted(reports))}", "",
           "Each `renderloop bench --versus-mitsuba` run writes its own report; this page keeps each scene's "
           "newest reading (per Mitsuba variant) and counts the issue's bars against the whole suite "
           "(scenes/dev and scenes/val): an unmeasured scene is not counted as ahead. Equal-error speed-up "
           "= the time the better `mi.render` + OIDN (the scene's own filter or a box film) needs to reach "
           "the loop's final SMAPE ÷ the loop's time; `~` marks a reading extrapolated from a power law "
           "fitted to the competitor's curve (each report says how). The speed-up at the competitor's last "
           "point needs no power law: each `mi.render` + OIDN's own highest-spp point (measured) against the "
           "loop's time to that error off the loop's own curve, the film least favourable to the loop (`≥`: "
           "the loop's first iteration is already as low, a lower bound; ‡: recomputed from the printed curve "
           "table of a report from before this reading, whose SMAPE has 4 decimals, so approximate). Runs "
           "differ in load and commit: "
           "each row names its report. SMAPE cannot read an error below the reference's own (for Gaussian "
           "noise of relative standard error s, a pixel's expected SMAPE against the truth is about "
           "s·√(2/π)/2 ≈ 0.4 s): where that floor is near the methods' SMAPE, both sit at it and the relMSE "
           "columns, with the references' variance taken out, separate them.", ""]
    for standing in standings:
        out += [f"## {VARIANT_LABELS.get(standing.variant, f'`{standing.variant}`')}", "", _verdict(standing), "",
                "| scene (film, filter) | equal-error speed-up (SMAPE) | equal-time SMAPE ratio | loop SMAPE | "
                "reference's relative error | equal-error speed-up (relMSE) | speed-up at the competitor's last point | "
                "loop peak RSS MB | report (commit, date; run) | earlier runs |",
                "|---|---:|---:|---:|---:|---:|---:|---:|---|---|"]
        for name in standing.suite:
            r = standing.newest.get(name)
            if r is None:
                continue
            earlier = ", ".join(f"{_speedup_text(o)} ({o.report}, {o.commit})" for o in standing.older.get(name, []))
            out.append(f"| {r.scene} ({r.film}) | **{_speedup_text(r)}** | {r.equal_time} | {r.loop_smape:.4f} | "
                       f"{r.reference_error:.4f} | {_speedup_cell(r.relmse_speedup, r.relmse_extrapolated)} | "
                       f"{r.end_speedup or '—'} | "
                       f"{r.peak_rss_mb:.0f} | [{r.report}]({r.report}) ({r.commit}, {r.date[:10]}; {r.settings}) | "
                       f"{earlier} |")
        if standing.unfair_to_stratifying:
            out += ["", "† A stratifying scene measured before the bench rendered it fairly: its reference kept the "
                    "scene's sampler, or `mi.render` + OIDN split each level into 16-spp calls (both at 2 MP). "
                    "Over 16 samples Mitsuba's `stratified` sampler is measurably biased: the first biases the "
                    "reference towards the competitor as written, the second handicaps the competitor "
                    "(`python -m bench.experiments.competitor_calls`); see docs/decisions.md."]
        if any(math.isinf(v) for r in standing.newest.values() for v in (r.speedup, r.relmse_speedup)):
            out += ["", f"§ The competitor never gets as low as the loop within its measured curve, and falls so "
                    f"slowly that its power law would reach the loop's error only beyond {EXTRAPOLATION_LIMIT:g}× its "
                    "last measured time, which is no estimate (a report from before this rule prints that guess: "
                    "~10⁴× and more). Counted as the "
                    "loop ahead; the speed-up at the competitor's last point, measured, carries the figure."]
        if standing.unmeasured:
            out += ["", f"Not yet measured ({len(standing.unmeasured)}): {', '.join(standing.unmeasured)}."]
        out.append("")
    return "\n".join(out)


def suite_reports(folder: Path) -> list[Path]:
    """The `--versus-mitsuba` reports in `folder`, the suite page itself left out."""
    return sorted(p for p in Path(folder).glob(REPORT_GLOB) if p.name != SUMMARY_NAME)


def cpu_standing(folder: Path) -> VariantStanding:
    """The suite's CPU standing over the reports in `folder`: each scene's newest reading, as the
    suite page has it."""
    standings = suite_standing(suite_reports(folder), suite_names(), stratifying_scenes())
    return next(s for s in standings if s.variant == "llvm_ad_rgb")


def write_suite_summary(folder: Path, command: str) -> Path:
    """Read every `--versus-mitsuba` report in `folder` and write the summary next to them."""
    folder = Path(folder)
    reports = suite_reports(folder)
    if not reports:
        raise ValueError(f"no {REPORT_GLOB} reports in {folder}/ (run renderloop bench --versus-mitsuba first)")
    out = folder / SUMMARY_NAME
    out.write_text(summary_text(suite_standing(reports, suite_names(), stratifying_scenes()), reports, command))
    return out


def run_suite_summary_command(args: argparse.Namespace) -> int:
    try:
        path = write_suite_summary(args.out, command_line())
    except ValueError as exc:  # no reports there, or a file that is not one
        print(f"renderloop bench: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {path}")
    return 0
