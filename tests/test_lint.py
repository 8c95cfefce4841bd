"""The linter: `ruff check` (pyflakes rules, unused imports, import order, syntax errors; the
rules in pyproject.toml's [tool.ruff]) is clean on the whole repository."""
from __future__ import annotations

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
