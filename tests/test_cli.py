"""The `dope-hope` entry point: help, `objects`, and the one-line error / exit 2 contract."""
from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys

import pytest

from dope_hope import cli
from dope_hope.catalog import HOPE_OBJECTS


def test_console_script_help():
    exe = shutil.which("dope-hope")
    cmd = [exe, "--help"] if exe else [sys.executable, "-m", "dope_hope.cli", "--help"]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "usage: dope-hope" in out.stdout
    for name, _, _ in cli.COMMANDS:
        assert name in out.stdout


def test_no_command_prints_help(capsys):
    assert cli.main([]) == 0
    assert "usage: dope-hope" in capsys.readouterr().out


def test_version(capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["--version"])
    assert exc.value.code == 0
    assert re.match(r"dope-hope \d+\.\d+", capsys.readouterr().out)


def test_objects_table(capsys):
    assert cli.main(["objects"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    header, rows = lines[0], lines[2:]
    for word in ("id", "name", "category", "size", "diam"):
        assert word in header
    assert len(rows) == 28
    for o, row in zip(HOPE_OBJECTS, rows):
        fields = row.split()
        assert int(fields[0]) == o.obj_id and fields[1] == o.name and fields[2] == o.category
        size = [float(v) for v in fields[3].split("/")]
        assert size == pytest.approx([100 * v for v in o.size], abs=0.006)  # cm, 2 decimals
        assert float(fields[4]) == pytest.approx(100 * o.diameter, abs=0.006)
    ketchup = next(r for r in rows if " Ketchup " in r)
    assert "6.45/14.86/4.34" in ketchup


def test_objects_json(capsys):
    assert cli.main(["objects", "--json"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert len(rows) == 28
    assert rows[10]["name"] == "Ketchup" and rows[10]["obj_id"] == 11
    assert rows[10]["size_m"] == pytest.approx(list(HOPE_OBJECTS[10].size))


def test_objects_mesh_prints_the_symmetries_training_and_evaluation_use(tmp_path, capsys):
    """--mesh: each mesh's symmetries in the resolution order, found ones with their BOP fields in
    the mesh's unit (a model_info.json to keep); a missing mesh or --units alone: one line, 2."""
    import trimesh

    cone = tmp_path / "Funnel" / "textured.obj"
    cone.parent.mkdir()
    trimesh.creation.cone(radius=3.0, height=8.0, sections=64).export(cone)  # cm
    assert cli.main(["objects", "--mesh", str(cone)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("Funnel: detected on the mesh: continuous about z")
    fields = json.loads(lines[1])
    assert fields == {"symmetries_continuous": [{"axis": [0.0, 0.0, 1.0], "offset": pytest.approx([0, 0, 4.0])}]}
    (cone.parent / "model_info.json").write_text(lines[1])  # kept beside the mesh: now declared
    assert cli.main(["objects", "--mesh", str(cone), "--json"]) == 0
    row = json.loads(capsys.readouterr().out)
    assert row["class"] == "Funnel" and row["symmetries"] == f"declared in {cone.parent / 'model_info.json'}"
    assert cli.main(["objects", "--mesh", str(tmp_path / "none.obj")]) == 2
    assert cli.main(["objects", "--units", "m"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "mesh file not found" in err[0] and "--units" in err[1]


def test_reader_error_exits_2_with_one_line(tmp_path, monkeypatch, capsys):
    """A DopeHopeError raised by a reader inside a command: one line on stderr, status 2."""
    bad = tmp_path / "000000.json"
    bad.write_text(json.dumps({"format": "dope-hope", "objects": [
        {"class": "Ketchup", "location": [0, 0, 50], "quaternion_xyzw": [0, 0, 0, 1],
         "projected_cuboid": [[0, 0]] * 8}]}))

    def run(args):
        from dope_hope.io.dope_json import read_dope_json
        read_dope_json(bad)
        return 0

    monkeypatch.setattr("dope_hope.commands.objects.run", run)
    assert cli.main(["objects"]) == 2
    captured = capsys.readouterr()
    err_lines = captured.err.strip().splitlines()
    assert len(err_lines) == 1
    assert err_lines[0] == (f"dope-hope objects: error: {bad}: "
                            "objects[0].projected_cuboid: expected 9 points, got 8")
    assert "Traceback" not in captured.err and captured.out == ""


def test_unknown_option_is_an_argparse_error(capsys):
    with pytest.raises(SystemExit) as exc:
        cli.main(["objects", "--no-such-option"])
    assert exc.value.code == 2
