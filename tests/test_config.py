"""Config lookup: names resolve to configs/NAME.yaml even when the working directory holds a
folder of that name (e.g. `dope-hope synth --out synth/ketchup`, then a second synth run)."""
from __future__ import annotations

import pytest

from dope_hope.config import CONFIG_DIR, config_path, load_config
from dope_hope.errors import ConfigError, InputFileError


def test_name_wins_over_a_folder_of_the_same_name(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "synth" / "ketchup").mkdir(parents=True)
    assert config_path("synth") == CONFIG_DIR / "synth.yaml"
    own = tmp_path / "mine.yaml"
    own.write_text("target: {count: [1, 1]}\n")
    assert config_path("mine.yaml").resolve() == own
    with pytest.raises(InputFileError):
        config_path("missing.yaml")
    with pytest.raises(ConfigError, match="unknown config 'nope'"):
        config_path("nope")


def test_demo_profile_is_one_box_in_range():
    cfg = load_config("demo")
    assert cfg["target"]["count"] == [1, 1] and cfg["target"]["distance_m"] == [0.45, 0.9]
    assert cfg["target"]["truncation_prob"] == 0.0
