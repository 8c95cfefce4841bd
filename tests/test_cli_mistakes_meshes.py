"""Meshes with no volume at the edges of `infer --mesh` (a new object), `objects --mesh` and
the unit hints, through the CLI: a non-finite vertex (which trimesh would drop with its
faces), a surface of zero area, a flat mesh, a regular tetrahedron's turns, files and a
folder mixed, the flag that gives a unit. Each ends in one line naming the file and what is
wrong, exit 2, nothing written; or (the tetrahedron) the whole answer.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from test_cli_mistakes import frames as frames  # noqa: PLC0414 - fixtures the tests take
from test_cli_mistakes import mesh as mesh  # noqa: PLC0414
from test_cli_mistakes import one_line_error, run_cli
from test_cli_mistakes_edges import grocery as grocery  # noqa: PLC0414 - fixtures the tests take
from test_cli_mistakes_edges import shelf as shelf  # noqa: PLC0414
from test_cli_mistakes_edges import shelf_run as shelf_run  # noqa: PLC0414

from dope_hope.assets import PRETRAINED_WEIGHTS

CUBE_CM = 5.0  # a 10 cm cube, centimetres (the OBJ default unit)


def cube_obj(path: Path, bad: str | None = None) -> Path:
    """A 10 cm cube as OBJ text (cm); ``bad`` replaces the last vertex's x."""
    box = trimesh.creation.box(extents=[2 * CUBE_CM] * 3)
    lines = [f"v {x:g} {y:g} {z:g}" for x, y, z in box.vertices]
    if bad is not None:
        lines[-1] = f"v {bad} " + " ".join(lines[-1].split()[2:])
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in box.faces]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    return path


def infer_new_object(image: Path, *meshes, out: Path) -> list:
    argv = ["infer", image]
    for m in meshes:
        argv += ["--mesh", m]
    return argv + ["--out", out, "--no-progress", "--no-overlay"]


needs_start = pytest.mark.skipif(not PRETRAINED_WEIGHTS.is_file(), reason="the pretrained start is not installed")


# ----------------------------------------------------------------------------- vertices
@pytest.mark.parametrize("command", ["infer", "objects"])
@pytest.mark.parametrize("value", ["nan", "inf"])
def test_a_non_finite_vertex_is_refused_naming_its_line(command, value, frames, tmp_path, capsys):
    bad = cube_obj(tmp_path / "MyCube.obj", value)
    out = tmp_path / "out"
    argv = infer_new_object(frames / "000000.png", bad, out=out) if command == "infer" else ["objects", "--mesh", bad]
    line = one_line_error(*run_cli(argv, capsys)[::2], command)
    assert f"{bad}: line 8 ('v {value} 5 5') is not a finite number (a mesh with a hole where it was would be read)" \
        in line
    assert not out.exists()


def test_a_non_finite_vertex_of_a_ply_is_refused_naming_its_index(tmp_path, capsys):
    box = trimesh.creation.box(extents=[100.0] * 3)  # mm
    vertices = box.vertices.copy()
    vertices[3, 1] = np.nan
    ply = tmp_path / "obj_000001.ply"
    trimesh.Trimesh(vertices, box.faces, process=False).export(ply, encoding="ascii")
    line = one_line_error(*run_cli(["objects", "--mesh", ply], capsys)[::2], "objects")
    assert f"{ply}: vertex 3 ([-50.0, nan, 50.0]) is not a finite number" in line


# ----------------------------------------------------------------------------- surface and volume
def write_obj(path: Path, vertices: list, faces: list) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(f"v {x:g} {y:g} {z:g}\n" for x, y, z in vertices)
                    + "".join(f"f {a} {b} {c}\n" for a, b, c in faces))
    return path


@pytest.mark.parametrize("command", ["infer", "objects"])
@pytest.mark.parametrize("shape, expected", [
    ("line", "mesh has no surface: its 1 triangle(s) have zero area"),
    ("flat", "mesh is flat: its box is 10 x 10 x 0 cm, zero along z; an object's cuboid needs three positive sides"),
])
def test_a_mesh_with_no_surface_or_no_volume_is_refused_naming_it(command, shape, expected, frames, tmp_path, capsys):
    vertices = {"line": [(0, 0, 0), (5, 0, 0), (10, 0, 0)], "flat": [(0, 0, 0), (10, 0, 0), (0, 10, 0)]}[shape]
    mesh = write_obj(tmp_path / "Tri.obj", vertices, [(1, 2, 3)])
    out = tmp_path / "out"
    argv = infer_new_object(frames / "000000.png", mesh, out=out) if command == "infer" else ["objects", "--mesh", mesh]
    line = one_line_error(*run_cli(argv, capsys)[::2], command)
    assert f"{mesh}: {expected}" in line
    assert "pretrained_lite.pt" not in line and not out.exists()


def test_objects_finds_the_turns_of_a_regular_tetrahedron(tmp_path, capsys):
    """Its three flips (about the box axes) and its eight 120-degree turns (about the axes
    through its vertices): 11 symmetries, the group of the tetrahedron."""
    corners = [(5, 5, 5), (5, -5, -5), (-5, 5, -5), (-5, -5, 5)]  # cm
    mesh = write_obj(tmp_path / "Tetra.obj", corners, [(1, 2, 3), (1, 4, 2), (1, 3, 4), (2, 4, 3)])
    code, out, err = run_cli(["objects", "--mesh", mesh, "--json"], capsys)
    assert code == 0, err
    row = json.loads(out)
    assert row["symmetries"].count("flip about") == 3 and row["symmetries"].count("3-fold turn about") == 4
    assert row["axes_tried"] == "the box axes x, y, z; 4 through the convex hull's vertices"
    turns = np.array(row["fields"]["symmetries_discrete"]).reshape(-1, 4, 4)
    assert len(turns) == 11
    angles = np.degrees(np.arccos(np.clip((np.trace(turns[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert sorted(np.round(angles).astype(int).tolist()) == [120] * 8 + [180] * 3
    for T in turns:  # each maps the corners onto the corners
        moved = np.asarray(corners) @ T[:3, :3].T + T[:3, 3]
        assert all(np.min(np.linalg.norm(np.asarray(corners) - p, axis=1)) < 1e-6 for p in moved)
    code, out, err = run_cli(["objects", "--mesh", mesh], capsys)
    assert code == 0 and out.splitlines()[-1] == "  axes tried: the box axes x, y, z; 4 through the convex hull's vertices"


# ----------------------------------------------------------------------------- files and a folder
@needs_start
def test_mesh_files_and_a_models_folder_mixed_are_refused(frames, tmp_path, capsys):
    cube = cube_obj(tmp_path / "MyCube.obj")
    folder = tmp_path / "models"
    cube_obj(folder / "Other.obj")
    out = tmp_path / "out"
    line = one_line_error(*run_cli(infer_new_object(frames / "000000.png", cube, folder, out=out), capsys)[::2],
                          "infer")
    assert (f"--mesh {folder}: a models folder, given with 1 other --mesh value(s); give either mesh files "
            "(--mesh [NAME=]FILE, repeated) or one models folder") in line
    assert "DemoBox" not in line and not out.exists()


# ----------------------------------------------------------------------------- the unit flag
@pytest.mark.parametrize("command, flag", [("synth", "--units"), ("infer", "--mesh-units"),
                                           ("objects", "--units")])
def test_a_unit_hint_names_the_flag_that_gives_it(command, flag, frames, tmp_path, capsys):
    can_m = tmp_path / "Can.obj"  # a 5 x 5 x 8 cm can written in metres, read as the OBJ's cm
    can_m.write_text(trimesh.exchange.obj.export_obj(trimesh.creation.cylinder(radius=0.025, height=0.08)))
    out = tmp_path / "out"
    argv = {"synth": ["synth", "--mesh", can_m, "--out", out, "--count", 1, "--size", "32x32", "--no-progress"],
            "infer": infer_new_object(frames / "000000.png", can_m, out=out),
            "objects": ["objects", "--mesh", can_m]}[command]
    line = one_line_error(*run_cli(argv, capsys)[::2], command)
    assert line.endswith(f"the file is likely in m: give its unit as m ({flag} m)")
    assert not out.exists()


# ----------------------------------------------------------------------------- a resumed run's mesh
def test_resume_with_a_mesh_named_for_no_object_of_the_run_is_refused(shelf_run, grocery, capsys):
    """`train --resume --mesh NAME=PATH` without --object: NAME is checked against the objects
    the run records, as --object would be."""
    milk = grocery / "Milk" / "textured.obj"
    before = {p.name: p.read_bytes() for p in shelf_run.iterdir() if p.is_file()}
    argv = ["train", "--out", shelf_run, "--resume", "--steps", 2, "--no-progress", "--mesh", f"Milk={milk}",
            "--units", "m"]
    line = one_line_error(*run_cli(argv, capsys)[::2], "train")
    assert f"--mesh Milk={milk}: Milk is not an object of this run (objects: Can, Cereal)" in line
    assert {p.name: p.read_bytes() for p in shelf_run.iterdir() if p.is_file()} == before


# ----------------------------------------------------------------------------- synth distractors
def test_synth_distractors_in_another_unit_are_read_in_theirs_with_a_warning(mesh, grocery, tmp_path, capsys):
    """The grocery can is in metres (5 x 5 x 8 cm): as an .obj it would be read in cm (0.5 mm)."""
    folder = tmp_path / "distractors"
    folder.mkdir()
    can = folder / "Can.obj"
    can.write_bytes((grocery / "Can" / "textured.obj").read_bytes())
    out = tmp_path / "out"
    code, _, err = run_cli(["synth", "--mesh", mesh, "--distractors", folder, "--out", out, "--count", 1,
                            "--size", "32x32", "--no-progress"], capsys)
    assert code == 0, err
    warned = [line for line in err.splitlines() if ": warning: " in line]
    assert len(warned) == 1 and warned[0].startswith(f"dope-hope synth: warning: --distractors {can}: box ")
    assert warned[0].endswith(" cm is no object's size in cm, its suffix's unit; read in m")
    assert (out / "000000.png").is_file()


@pytest.mark.parametrize("shape, expected", [
    ("flat", "mesh is flat: its box is 10 x 10 x 0 cm, zero along z"),
    ("huge", "mesh box 1e+06 x 1e+06 x 1e+06 cm (read in cm) is too large for an object (largest side over 5 m); "
             "no unit (m, cm, mm) makes it an object's size"),
    ("nan", "line 8 ('v nan 5 5') is not a finite number"),
])
def test_synth_distractors_no_unit_makes_an_object_are_refused_before_any_frame(shape, expected, mesh, tmp_path,
                                                                                capsys):
    folder = tmp_path / "distractors"
    bad = {"flat": lambda p: write_obj(p, [(0, 0, 0), (10, 0, 0), (0, 10, 0)], [(1, 2, 3)]),
           "huge": lambda p: write_obj(p, [(0, 0, 0), (1e6, 0, 0), (0, 1e6, 0), (0, 0, 1e6)],
                                       [(1, 2, 3), (1, 4, 2), (1, 3, 4), (2, 4, 3)]),
           "nan": lambda p: cube_obj(p, "nan")}[shape](folder / "Bad.obj")
    out = tmp_path / "out"
    line = one_line_error(*run_cli(["synth", "--mesh", mesh, "--distractors", folder, "--out", out, "--count", 1,
                                    "--size", "32x32", "--no-progress"], capsys)[::2], "synth")
    assert f"{bad}: {expected}" in line
    assert not out.exists()
