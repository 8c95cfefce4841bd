"""dope_hope.staged_run.CommandStages: a stage runs once, leaves its marker and log, is skipped
when run again; a failed stage leaves no marker and names its log."""
import json

import pytest

from dope_hope.staged_run import CommandStages


def test_a_stage_runs_once_and_is_skipped_when_done(tmp_path, capsys):
    stages = CommandStages(tmp_path / "job")
    stages.stage("objects", ["objects"])
    marker = json.loads((tmp_path / "job" / "stages" / "objects.json").read_text())
    assert marker["command"] == "dope-hope objects" and marker["seconds"] >= 0
    log = (tmp_path / "job" / "logs" / "objects.log").read_text()
    assert log.startswith("$ dope-hope objects\n") and "Ketchup" in log  # the command's own output
    assert not (tmp_path / "job" / "stages" / "other.json").exists()

    again = CommandStages(tmp_path / "job")
    again.stage("objects", ["objects", "--no-such-option"])  # skipped: never run, so never fails
    assert "done earlier, skipped" in capsys.readouterr().out
    assert again.timings["objects"] == marker["seconds"]


def test_a_failed_stage_leaves_no_marker_and_names_its_log(tmp_path):
    stages = CommandStages(tmp_path)
    for attempt in range(2):
        with pytest.raises(SystemExit, match=r"\[bad\] failed with status 2 .* log .*bad\.log"):
            stages.stage("bad", ["objects", "--no-such-option"])
        assert not (tmp_path / "stages" / "bad.json").exists()
    assert (tmp_path / "logs" / "bad.log").read_text().count("$ dope-hope objects --no-such-option") == 2


def test_a_jobs_settings_are_recorded_once_and_a_change_is_named(tmp_path):
    from dope_hope.staged_run import settings_changed

    path = tmp_path / "job" / "settings.json"
    settings = {"count": 16, "scene": ["a=1"], "train": {"seed": 0}}
    assert settings_changed(path, settings) == [] and json.loads(path.read_text()) == settings
    assert settings_changed(path, settings) == []                                   # the same job: on
    assert settings_changed(path, {**settings, "count": 8, "train": {"seed": 1}}) == ["count", "train.seed"]
    assert json.loads(path.read_text()) == settings                                 # the record stays
