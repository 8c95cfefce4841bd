"""The linter: `ruff check` (pyflakes rules, unused imports, import order, syntax errors, imports at
the top of library modules; the rules in pyproject.toml's [tool.ruff]) is clean on the whole
repository, and every nested import of the library says why it is nested."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_ruff_finds_nothing_on_the_repository():
    result = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", str(REPO)], cwd=REPO,
                            capture_output=True, text=True)
    assert "No module named ruff" not in result.stderr, "ruff is missing: pip install -e '.[dev]'"
    assert result.returncode == 0, f"ruff check:\n{result.stdout}{result.stderr}"


def test_ruff_reports_an_unused_import(tmp_path):
    """The check can fail: an unused import and an unsorted import block are reported."""
    bad = tmp_path / "bad.py"
    bad.write_text("import sys\nimport os\n")
    result = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", "--config",
                             str(REPO / "pyproject.toml"), str(bad)], cwd=tmp_path, capture_output=True, text=True)
    assert result.returncode == 1
    assert "F401" in result.stdout and "I001" in result.stdout


#: A nested import's noqa with its reason: ``# noqa: PLC0415 (why)``, other codes may come first.
REASONED_NOQA = re.compile(r"#\s*noqa:[^#]*\bPLC0415\b[^#(]*\(\s*\S[^)]*")


def bare_nested_imports(root: Path) -> list[str]:
    """``file:line`` of each ``noqa: PLC0415`` under ``root`` without a reason in parentheses."""
    found = []
    for path in sorted(root.rglob("*.py")):
        for number, line in enumerate(path.read_text().splitlines(), 1):
            if "PLC0415" in line and not REASONED_NOQA.search(line):
                found.append(f"{path.relative_to(root)}:{number}")
    return found


def test_every_nested_library_import_gives_its_reason():
    assert bare_nested_imports(REPO / "dope_hope") == []


def test_nested_imports_are_reported_and_a_bare_noqa_is_caught(tmp_path):
    """The rule can fail: a nested import in a library module is reported by ruff, and a noqa
    without a reason is caught by the reason check."""
    package = tmp_path / "dope_hope"
    package.mkdir()
    (package / "mod.py").write_text("def f():\n    import json\n\n    return json\n")
    result = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", "--config",
                             str(REPO / "pyproject.toml"), str(package / "mod.py")], cwd=tmp_path,
                            capture_output=True, text=True)
    assert result.returncode == 1 and "PLC0415" in result.stdout
    (package / "mod.py").write_text("def f():\n    import json  # noqa: PLC0415\n\n    return json\n"
                                    "def g():\n    import os  # noqa: PLC0415 (only for g)\n\n    return os\n")
    assert bare_nested_imports(tmp_path) == ["dope_hope/mod.py:2"]
