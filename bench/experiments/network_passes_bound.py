"""How far speed work on the loop's networks alone could take the 2 MP speed-ups: the suite re-read
with every network pass but the one that makes each image free.

A `mi.render` + OIDN point pays one OIDN call for its image; a loop point at 128 spp paid four
denoise and error passes, three of them only to allocate the next samples. For each scene of the
suite's newest CPU reading (the suite page's), the loop's printed curve is re-timed from its report's
stage table: a point's time becomes the render and allocation seconds of every iteration so far plus
the denoise and error seconds of its own iteration alone. Its errors stay as printed: the bound
assumes the allocation those passes fed, at no cost. Against it stand the competitors re-timed with
their features rendered apart (docs/competitor-features.md: `bench.experiments.competitor_features`),
through the same readings as the suite page (bench.versus_mitsuba_run.better_of,
least_at_competitor_ends). If the bars are out of reach even so, no cut of the networks' fixed costs
meets them on this CPU: the loop's images at equal samples must get better.

    python -m bench.experiments.network_passes_bound [--reports docs]
        [--costs-from docs/competitor-features.md] [-o FILE]
"""
from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

from bench.common import experiment_command, provenance, publish
from bench.experiments.competitor_features import (costs_from_report, readings_summary, speedup_text, suite_curves,
                                                   suite_readings)
from bench.versus_mitsuba_report import LOOP_STAGES
from bench.versus_mitsuba_run import Curve, CurvePoint
from bench.versus_mitsuba_suite import Reading, cpu_standing, suite_names, table_rows

STAGE_HEADER = "| scene | iteration | spp | " + " | ".join(LOOP_STAGES) + " | total s |"
NETWORK_STAGES = ("denoise", "error")   # the passes a point needs once, for its own image


def stage_seconds(report_lines: list[str], scene: str) -> list[dict[str, float]]:
    """Per iteration of the loop (error allocator) in a report's stage table, its seconds per stage."""
    rows = [row for row in table_rows(report_lines, STAGE_HEADER) if row[0] == scene]
    return [dict(zip(LOOP_STAGES, (float(cell) for cell in row[3:3 + len(LOOP_STAGES)]))) for row in rows]


def one_pass_per_point(loop: Curve, stages: list[dict[str, float]]) -> Curve:
    """`loop` with point k's time = Σ_{i ≤ k} (render_i + allocate_i) + denoise_k + error_k: its own
    image's networks paid, the earlier iterations' free."""
    if len(stages) != len(loop.points):
        raise ValueError(f"{loop.key}: {len(loop.points)} curve points but {len(stages)} stage rows")
    points, sampling = [], 0.0
    for point, seconds in zip(loop.points, stages):
        sampling += sum(v for stage, v in seconds.items() if stage not in NETWORK_STAGES)
        own = sum(seconds[stage] for stage in NETWORK_STAGES)
        points.append(CurvePoint(point.spp, sampling + own, point.smape, point.stages, point.relmse))
    return Curve(loop.key, loop.label, points)


@dataclass(frozen=True)
class BoundRow:
    reading: Reading
    loop_seconds: float        # the loop's last point as measured
    bound_seconds: float       # the same point with one network pass
    smape: tuple[tuple[float, str], tuple[float, str]]    # (as measured, bound): (speed-up, how read)
    relmse: tuple[tuple[float, str], tuple[float, str]]
    end: tuple[float, float]   # SMAPE at the competitors' last points: as measured, bound


def bound_row(reading: Reading, loop: Curve, competitors: list[Curve], stages: list[dict[str, float]]) -> BoundRow:
    bound = one_pass_per_point(loop, stages)
    measured, free = suite_readings(loop, competitors), suite_readings(bound, competitors)
    return BoundRow(reading, loop.points[-1].seconds, bound.points[-1].seconds, (measured.smape, free.smape),
                    (measured.relmse, free.relmse), (measured.end, free.end))


def report_text(rows: list[BoundRow], command: str) -> str:
    lines = ["# The 2 MP suite with the loop's intermediate network passes free", "", provenance(command), "",
             " ".join(__doc__.split("\n\n")[1].split()), "",
             "Speed-ups over the better competitor, `~`: read off the competitor's fitted power law; at the "
             "competitors' last points the least favourable of the two films.", "",
             "| scene (film) | report | loop s | one pass a point s | SMAPE speed-up | bound | relMSE speed-up "
             "| bound | at the competitors' last points | bound |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for row in rows:
        cells = [f"{row.reading.scene} ({row.reading.film})", row.reading.report, f"{row.loop_seconds:.1f}",
                 f"{row.bound_seconds:.1f}", *(speedup_text(*reading) for pair in (row.smape, row.relmse)
                                               for reading in pair),
                 f"{row.end[0]:.2f}×", f"{row.end[1]:.2f}×"]
        lines.append("| " + " | ".join(cells) + " |")
    def both(readings: list[tuple]) -> tuple[list[float], list[float]]:
        return [r[0] for r in readings], [r[1] for r in readings]

    lines += ["", f"Over {len(rows)} scenes, " + readings_summary(
        "as measured", "bound", both([(r.smape[0][0], r.smape[1][0]) for r in rows]),
        both([(r.relmse[0][0], r.relmse[1][0]) for r in rows]), both([r.end for r in rows]))]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--reports", type=Path, default=Path("docs"))
    parser.add_argument("--costs-from", type=Path, default=Path("docs/competitor-features.md"),
                        help="the competitors' feature costs (bench.experiments.competitor_features' report)")
    parser.add_argument("-o", "--out", type=Path, default=None, help="write the report here too")
    args = parser.parse_args(argv)
    standing = cpu_standing(args.reports)
    costs = costs_from_report(args.costs_from)
    rows = []
    for name in suite_names():
        reading = standing.newest.get(name)
        if reading is None:
            continue
        report = args.reports / reading.report
        loop, competitors = suite_curves(reading, report, costs)
        rows.append(bound_row(reading, loop, competitors, stage_seconds(report.read_text().splitlines(), name)))
    command = experiment_command("bench.experiments.network_passes_bound", argv)
    text = report_text(rows, command)
    publish(text, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
