"""tools/pretrain_start.py, a CommandStages job: the default recipe runs the shipped start's
commands; a work folder holding a run of other settings is refused (exit status 2, naming what
differs) before any stage runs, and rerunning the same command goes on (the stages resume)."""
import importlib.util
import sys
from pathlib import Path

import pytest

TOOL = Path(__file__).resolve().parent.parent / "tools" / "pretrain_start.py"


@pytest.fixture
def tool(monkeypatch):
    """The tool as a module, its stages and export recorded instead of run."""
    spec = importlib.util.spec_from_file_location("pretrain_start", TOOL)
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, module)  # its dataclass looks itself up there
    spec.loader.exec_module(module)
    module.ran = []
    monkeypatch.setattr(module.CommandStages, "stage", lambda self, name, argv: module.ran.append((name, argv)))
    monkeypatch.setattr(module, "save_inference_checkpoint", lambda src, dst, source: dst)
    return module


def _photos(tmp_path: Path) -> Path:
    photos = tmp_path / "photos"
    photos.mkdir()
    (photos / "scene.png").write_bytes(b"not read here")
    return photos


def test_the_default_recipe_is_the_shipped_starts_and_another_is_refused_in_its_folder(tool, tmp_path, capsys):
    photos, out = _photos(tmp_path), tmp_path / "pre"
    assert tool.main(["--out", str(out), "--photos", str(photos), "--init", "start_v1.pt"]) == 0
    commands = {name: [str(a) for a in argv] for name, argv in tool.ran}
    assert list(commands) == ["synth-train", "synth-val", "train"]
    synth = commands["synth-train"]
    assert synth[synth.index("--config") + 1] == "procedural" and synth[synth.index("--seed") + 1] == "31"
    assert commands["synth-val"][commands["synth-val"].index("--seed") + 1] == "32"
    assert "--backgrounds" in synth and str(photos) in synth
    train = commands["train"]
    assert train[train.index("--steps") + 1] == "16000" and train[train.index("--init") + 1] == "start_v1.pt"
    assert train[-1] == "train.calibrate_thresholds=false"  # a start records no threshold

    tool.ran.clear()
    with pytest.raises(SystemExit) as stop:
        tool.main(["--out", str(out), "--photos", str(photos), "--init", "start_v1.pt", "--recipe", "wide"])
    assert stop.value.code == 2 and tool.ran == []
    error = capsys.readouterr().err.strip().splitlines()[-1]
    assert f"--out {out.resolve()}: holds a run with other settings" in error and "recipe" in error

    assert tool.main(["--out", str(out), "--photos", str(photos), "--init", "start_v1.pt"]) == 0  # the same: on
    assert [name for name, _ in tool.ran] == ["synth-train", "synth-val", "train"]


@pytest.mark.parametrize("flag", ["--steps", "--count", "--val-count"])
def test_a_count_under_one_is_refused_before_anything_is_written(tool, tmp_path, capsys, flag):
    photos, out = _photos(tmp_path), tmp_path / "pre"
    with pytest.raises(SystemExit) as stop:
        tool.main(["--out", str(out), "--photos", str(photos), "--init", "start_v1.pt", flag, "0"])
    assert stop.value.code == 2 and tool.ran == [] and not out.exists()
    assert capsys.readouterr().err.strip().splitlines()[-1].endswith(f"{flag} 0: must be at least 1")
