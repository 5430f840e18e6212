"""What the code and the README point a reader to exists (issue 46): the code's and scripts'
references to docs/ name pages in the repository (none names the design notes' old home,
DESIGN.md, outside it), every `docs/decisions.md, "title"` citation names a paragraph there, and the README's Reports table links every report `renderloop bench`
writes into docs/. tests/test_docs_links.py checks the Markdown pages themselves."""
from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# Where code, set-up and packaging live (tests/ name their own fixtures, docs/ are checked elsewhere).
CODE_ROOTS = ("service", "models", "bench", "scripts", "docker", "Makefile", "pyproject.toml")
TEXT_SUFFIXES = {".py", ".sh", ".toml", ".yaml", ".yml", ".html", ".js", ".css", ".md", ".cpu", ".cuda", ""}
DOCS_PATH = re.compile(r"(?<![\w./-])docs/[\w./-]*\w")
# A generated report names the command that wrote it near its top (bench/templates/*.md).
REPORT_COMMAND = re.compile(r"^Command: `renderloop bench", re.MULTILINE)


def code_files() -> list[Path]:
    """The text files under CODE_ROOTS (no git needed: a source archive is checked the same)."""
    files = []
    for root in (REPO / name for name in CODE_ROOTS):
        candidates = [root] if root.is_file() else sorted(root.rglob("*"))
        files += [p for p in candidates if p.is_file() and p.suffix in TEXT_SUFFIXES and "__pycache__" not in p.parts]
    return files


def test_every_docs_page_the_code_names_is_in_the_repository():
    dead = []
    for path in code_files():
        text = path.read_text(encoding="utf-8", errors="replace")
        dead += [f"{path.relative_to(REPO)}: {ref}" for ref in DOCS_PATH.findall(text)
                 if not (REPO / ref.rstrip(".")).exists()]
        if "DESIGN.md" in text:
            dead.append(f"{path.relative_to(REPO)}: DESIGN.md (the design is docs/design.md)")
    assert dead == []


def generated_reports() -> list[str]:
    return sorted(page.name for page in (REPO / "docs").glob("*.md")
                  if REPORT_COMMAND.search("\n".join(page.read_text(encoding="utf-8").splitlines()[:6])))


def test_the_readme_links_every_report_renderloop_bench_writes_into_docs():
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    reports = generated_reports()
    assert "val-quality.md" in reports and "design.md" not in reports   # the detection itself
    assert [name for name in reports if f"](docs/{name})" not in readme] == []


# `docs/decisions.md, "A paragraph's title"` (the title may wrap, code comments may put '#' at a
# line start): the way code and pages cite the decision behind them.
DECISION_CITATION = re.compile(r'decisions\.md,\s+"([^"]{5,200})"')


def squeeze(text: str) -> str:
    return re.sub(r"\s+", " ", re.sub(r"\n\s*#", "\n", text))


def test_every_cited_decision_is_a_paragraph_of_the_decisions_page():
    decisions = squeeze((REPO / "docs" / "decisions.md").read_text(encoding="utf-8"))
    citing = code_files() + sorted((REPO / "docs").glob("*.md")) + [REPO / "README.md"]
    missing = [f"{path.relative_to(REPO)}: {title}"
               for path in citing
               for title in map(squeeze, DECISION_CITATION.findall(path.read_text(encoding="utf-8", errors="replace")))
               if title.rstrip(".,") not in decisions]
    assert missing == []
