"""The documents hold together: links resolve, every command option has its page with the
description `--help` gives it, the bench/RESULTS.md and bench/EXPERIMENTS.md sections that code
and configs point to exist, and every figure of the README's table of current figures stands in
a line of the RESULTS.md section it links."""
from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from dope_hope import cli

REPO = Path(__file__).resolve().parent.parent
RESULTS = REPO / "bench" / "RESULTS.md"
EXPERIMENTS = REPO / "bench" / "EXPERIMENTS.md"
DOCS = [REPO / "README.md", RESULTS, EXPERIMENTS, *sorted((REPO / "docs").rglob("*.md"))]
LINK = re.compile(r"\]\(([^)\s]+)\)")


def slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """The anchors of every heading of a Markdown file (outside code blocks)."""
    found, inside = set(), False
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.startswith("```"):
            inside = not inside
        elif not inside and line.startswith("#"):
            found.add(slug(line.lstrip("#")))
    return found


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(REPO)))
def test_relative_links_resolve(doc):
    for target in LINK.findall(doc.read_text(encoding="utf-8")):
        if re.match(r"[a-z]+:", target):
            continue  # http(s):, mailto:
        file, _, anchor = target.partition("#")
        path = (doc.parent / file).resolve() if file else doc
        assert path.exists(), f"{doc.name}: link to a missing file: {target}"
        if anchor and path.suffix == ".md":
            assert anchor in anchors(path), f"{doc.name}: no heading for #{anchor} in {path.name}"


def subcommands() -> dict[str, argparse.ArgumentParser]:
    (sub,) = [a for a in cli.build_parser()._actions if isinstance(a, argparse._SubParsersAction)]
    return dict(sub.choices)


def test_every_command_option_is_documented_on_its_page():
    for name, parser in subcommands().items():
        page = REPO / "docs" / "commands" / f"{name}.md"
        assert page.is_file(), f"no docs page for `dope-hope {name}`"
        text = page.read_text(encoding="utf-8")
        for action in parser._actions:
            for option in action.option_strings:
                if option not in ("-h", "--help"):
                    assert re.search(rf"(?<![\w-]){re.escape(option)}(?![\w-])", text), \
                        f"{page.name}: option {option} is not documented"


#: A row of a command page's options table: | `--option METAVAR` | description |
OPTION_ROW = re.compile(r"^\| `(-[^`]+)` \| (.*) \|\s*$", re.M)


def _plain(text: str) -> str:
    """Text as a reader sees it: no Markdown code or emphasis marks, whitespace collapsed."""
    return " ".join(re.sub(r"[`*]", "", text).split())


def test_option_descriptions_match_help():
    """Each row of a command page's options table says what `--help` says of the option (the
    help text is the source: fix it there, then copy it here)."""
    wrong = []
    for name, parser in subcommands().items():
        text = (REPO / "docs" / "commands" / f"{name}.md").read_text(encoding="utf-8")
        for key, description in OPTION_ROW.findall(text):
            actions = [a for a in parser._actions
                       if any(re.search(rf"(^|, ){re.escape(o)}(?![\w-])", key) for o in a.option_strings)]
            assert actions, f"{name}.md: the options table names {key}, which `dope-hope {name}` lacks"
            expected = _plain((actions[0].help or "").replace("%%", "%"))
            if _plain(description) != expected:
                wrong.append(f"{name}.md {key}:\n  page: {_plain(description)}\n  help: {expected}")
    assert not wrong, "option descriptions that differ from --help:\n" + "\n".join(wrong)


def section_headings(path: Path) -> set[str]:
    """The ``## `` headings of a Markdown page."""
    return {line[3:].strip() for line in path.read_text(encoding="utf-8").splitlines() if line.startswith("## ")}


@pytest.mark.parametrize("page", [RESULTS, EXPERIMENTS], ids=lambda p: p.name)
def test_results_sections_named_in_the_repository_exist(page):
    headings = section_headings(page)
    pointer = re.compile(rf'{page.stem}(?:\.md)?,? "([^"\n]+)"')
    files = [*(REPO / "dope_hope").rglob("*.py"), *(REPO / "dope_hope" / "configs").glob("*.yaml"),
             *(REPO / "bench").glob("*.py"), *DOCS]
    for path in files:
        for name in pointer.findall(path.read_text(encoding="utf-8")):
            assert any(h == name or h.startswith(name) for h in headings), \
                f"{path.relative_to(REPO)} points to a {page.name} section that does not exist: {name!r}"


def test_every_results_section_keeps_its_experiments():
    """RESULTS.md holds the current figures; the runs behind them stay in EXPERIMENTS.md under
    the same section names."""
    assert section_headings(RESULTS) <= section_headings(EXPERIMENTS)


def results_lines(path: Path = RESULTS) -> dict[str, list[str]]:
    """{anchor of a ``## `` section: its table lines} of RESULTS.md."""
    out: dict[str, list[str]] = {}
    anchor = None
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.startswith("## "):
            anchor = slug(line[3:])
            out[anchor] = []
        elif anchor and line.startswith("| ") and not line.startswith("| figure"):
            out[anchor].append(line)
    return out


#: A figure in a README row: a decimal number, or a whole one followed by its unit.
FIGURE = re.compile(r"(?<![\w.,\[])(\d[\d,]*\.\d+|\d[\d,]*(?= ?(?:%|x\b|ms|frames|s\b|px|crops|of\b)))")


def untraced_figures(readme: str, sections: dict[str, list[str]]) -> list[str]:
    """The figures of the README's "Current figures" table that no line of the RESULTS.md
    sections its row links holds."""
    table = readme.split("\n## Current figures\n", 1)[1].split("\n## ", 1)[0]
    missing = []
    for row in table.splitlines():
        if not row.startswith("| ["):
            continue
        anchors = re.findall(r"RESULTS\.md#([\w-]+)", row)
        lines = [line for a in anchors for line in sections.get(a, [])]
        for figure in FIGURE.findall(row.split(") | ", 1)[1]):
            if not any(re.search(rf"(?<![\d.]){re.escape(figure)}(?!\d)", line) for line in lines):
                missing.append(f"{anchors[0] if anchors else row[:40]}: {figure}")
    return missing


def test_readme_figures_stand_in_results():
    assert untraced_figures((REPO / "README.md").read_text(encoding="utf-8"), results_lines()) == []


def test_the_figure_check_catches_a_figure_results_lacks():
    readme = "\n## Current figures\n\n| [X](bench/RESULTS.md#x) | 4.4x faster, 12 of 30 found, 2 cores |\n"
    assert untraced_figures(readme, {"x": ["| **4.4x** faster, 12 of 30 | cmd |"]}) == []
    assert untraced_figures(readme, {"x": ["| 4.3x faster, 12 of 30 | cmd |"]}) == ["x: 4.4"]
