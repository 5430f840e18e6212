"""Rewrite the `--help` blocks of docs/cli.md from the parsers themselves.

docs/cli.md is prose and examples by hand, plus one block per command between
`<!-- help: NAME -->` and `<!-- /help -->` holding exactly what `renderloop NAME --help`
prints (at 100 columns). Run after changing a flag:

    .venv/bin/python scripts/cli_reference.py          # rewrites docs/cli.md in place
    .venv/bin/python scripts/cli_reference.py --check  # exit 1 if a block is out of date
"""
from __future__ import annotations

import argparse
import os
import re
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
CLI_PAGE = REPO / "docs" / "cli.md"
HELP_COLUMNS = "100"
HELP_BLOCK = re.compile(r"(<!-- help: (?P<name>[\w-]+) -->\n)(?P<body>.*?)(<!-- /help -->)", re.S)


def command_parsers() -> dict[str, argparse.ArgumentParser]:
    """`renderloop`'s own parser under "", then each command's; bench's is its own parser."""
    sys.path.insert(0, str(REPO))
    from bench.cli import build_parser as build_bench_parser
    from service.cli import build_parser

    parser = build_parser()
    subparsers = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    parsers = {"": parser, **subparsers.choices}
    parsers["bench"] = build_bench_parser()
    return parsers


def help_text(parser: argparse.ArgumentParser) -> str:
    os.environ["COLUMNS"] = HELP_COLUMNS  # argparse wraps to the terminal's width
    return parser.format_help()


def rendered_page(page: str, parsers: dict[str, argparse.ArgumentParser]) -> str:
    def block(match: re.Match) -> str:
        name = match.group("name")
        parser = parsers["" if name == "renderloop" else name]
        return f"{match.group(1)}```text\n{help_text(parser)}```\n{match.group(4)}"

    return HELP_BLOCK.sub(block, page)


def main(argv: list[str] | None = None) -> int:
    args = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    args.add_argument("--check", action="store_true", help="exit 1 if docs/cli.md is out of date")
    check = args.parse_args(argv).check
    page = CLI_PAGE.read_text(encoding="utf-8")
    fresh = rendered_page(page, command_parsers())
    if check:
        if fresh != page:
            print("docs/cli.md is out of date: run .venv/bin/python scripts/cli_reference.py", file=sys.stderr)
            return 1
        return 0
    CLI_PAGE.write_text(fresh, encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
