"""The README and docs/ name only files that are in the repository.

Three kinds of reference are checked in README.md and every Markdown file under docs/:
Markdown links and images (relative to the page), repository paths written in the text
(`service/loop/spec.py`, `docs/models.md`, relative to the repository root), and the modules
of `python -m pkg.module` commands. Web addresses and in-page anchors are not checked; in
docs/decisions.md, whose commands name code as it was at a cited commit, only links are.
docs/cli.md must also list every flag of every command, and the README stay short.
"""
from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
# A record of what was tried: its commands and paths name code as it was at the cited commit,
# often since removed; only its Markdown links must lead somewhere.
HISTORY_PAGES = {REPO / "docs" / "decisions.md"}
README_MAX_LINES = 250
OTHER_PROGRAMS_FLAGS = {"--head"}  # `ray start --head`, named in serve --ray-address's help

# [text](target) and ![alt](target); the target ends at whitespace or the closing parenthesis.
MARKDOWN_LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
# A path into one of the repository's top-level folders, written anywhere in the text.
TOP_LEVEL = ("service", "models", "bench", "scenes", "scripts", "tests", "docs", "docker")
REPO_PATH = re.compile(r"(?<![\w./$-])((?:" + "|".join(TOP_LEVEL) + r")/[\w./-]*[\w/])")
PYTHON_MODULE = re.compile(r"python -m ((?:" + "|".join(TOP_LEVEL) + r")(?:\.\w+)+)")


def markdown_pages() -> list[Path]:
    return [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]


def _is_external(target: str) -> bool:
    return bool(re.match(r"^[a-z][a-z0-9+.-]*:", target)) or target.startswith("#")


def dead_markdown_links(page: Path, text: str) -> list[str]:
    dead = []
    for target in MARKDOWN_LINK.findall(text):
        if _is_external(target):
            continue
        path = target.split("#", 1)[0]
        if path and not (page.parent / path).exists():
            dead.append(target)
    return dead


def dead_repository_paths(page: Path, text: str) -> list[str]:
    dead = []
    for path in REPO_PATH.findall(text):
        path = path.rstrip(".")
        if not path or (REPO / path).exists() or (page.parent / path).exists():
            continue
        if (REPO / (path.split(".", 1)[0] + ".py")).exists():  # module.attribute, e.g. loop/allocate.floor
            continue
        dead.append(path)
    return dead


def dead_python_modules(text: str) -> list[str]:
    dead = []
    for module in PYTHON_MODULE.findall(text):
        as_path = REPO / module.replace(".", "/")
        if not (as_path.with_suffix(".py").exists() or (as_path / "__main__.py").exists()):
            dead.append(f"python -m {module}")
    return dead


def page_id(page: Path) -> str:
    return str(page.relative_to(REPO))


@pytest.mark.parametrize("page", markdown_pages(), ids=page_id)
def test_every_link_and_path_in_the_docs_names_a_file_in_the_repository(page: Path) -> None:
    text = page.read_text(encoding="utf-8")
    dead = dead_markdown_links(page, text)
    if page not in HISTORY_PAGES:
        dead += dead_repository_paths(page, text) + dead_python_modules(text)
    assert not dead, f"{page_id(page)} names files that are not in the repository: {sorted(set(dead))}"


def test_the_link_check_finds_a_dead_link_a_dead_path_and_a_dead_module(tmp_path: Path) -> None:
    page = REPO / "docs" / "example.md"
    text = ("[gone](no-such-page.md) [there](design.md#the-loop) ![pic](page.png) [web](https://x.org)\n"
            "see `service/no_such_module.py` and service/loop/spec.py.\n"
            "python -m bench.no_such_report, python -m bench.cli\n")
    assert dead_markdown_links(page, text) == ["no-such-page.md"]
    assert dead_repository_paths(page, text) == ["service/no_such_module.py"]
    assert dead_python_modules(text) == ["python -m bench.no_such_report"]


def test_the_readme_fits_in_250_lines() -> None:
    lines = (REPO / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines, at most {README_MAX_LINES}"


def _cli_reference():
    spec = importlib.util.spec_from_file_location("cli_reference", REPO / "scripts" / "cli_reference.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_docs_cli_md_lists_every_flag_of_every_command_and_no_other() -> None:
    parsers = _cli_reference().command_parsers()
    page = (REPO / "docs" / "cli.md").read_text(encoding="utf-8")
    flags = {(name, option) for name, parser in parsers.items() for action in parser._actions
             for option in action.option_strings if option.startswith("--")}
    missing = sorted(f"renderloop {name} {option}" for name, option in flags if option not in page)
    known = {option for _, option in flags}
    examples = [line.split("#", 1)[0] for line in page.splitlines() if line.lstrip().startswith("renderloop ")]
    help_blocks = re.findall(r"<!-- help: [\w-]+ -->(.*?)<!-- /help -->", page, re.S)
    # A whole flag: not the first half of one argparse wrapped at a hyphen (`--token-⏎file`).
    written = re.findall(r"(?<![\w-])--[a-z][\w-]*[a-z0-9](?![\w-])", "\n".join(examples + help_blocks))
    unknown = sorted(set(written) - known - OTHER_PROGRAMS_FLAGS)
    assert not missing, f"docs/cli.md lacks {missing}: run .venv/bin/python scripts/cli_reference.py"
    assert not unknown, f"docs/cli.md names flags no command has: {unknown}"
