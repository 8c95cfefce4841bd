"""Configs and settings: names resolve to configs/NAME.yaml even when the working directory
holds a folder of that name (e.g. `dope-hope synth --out synth/ketchup`, then a second synth
run); the one settings loader (defaults, file, --set), its one-line errors, the recipes that
hold only what they change, and every command's --config / --set / `dope-hope settings`."""
from __future__ import annotations

import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

from dope_hope.config import (
    CONFIG_DIR,
    SectionSettings,
    at_least,
    changed_settings,
    config_path,
    load_config,
    load_settings,
    one_of,
    parse_assignment,
    section,
)
from dope_hope.errors import ConfigError, InputFileError
from dope_hope.inference.options import InferenceOptions
from dope_hope.synth.settings import SynthSettings
from dope_hope.training.settings import TrainConfig


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


# ----------------------------------------------------------------------------- settings
@dataclass(frozen=True)
class _Inner(SectionSettings):
    SECTION = "outer.inner"
    RULES = {"mode": one_of("a", "b")}
    mode: str = "a"


@dataclass(frozen=True)
class _Outer(SectionSettings):
    SECTION = "outer"
    RULES = {"count": at_least(1)}
    count: int = 2
    inner: _Inner = section(_Inner)


@dataclass(frozen=True)
class _Root(SectionSettings):
    SECTION = ""
    outer: _Outer = section(_Outer)


def test_loader_layers_defaults_file_and_set_items(tmp_path):
    """load_settings: defaults, then the file (deep-merged), then each --set item."""
    f = tmp_path / "mine.yaml"
    f.write_text("outer: {inner: {mode: b}}\n")
    s = load_settings(_Root, f, ["outer.count=5"])
    assert s.outer.count == 5 and s.outer.inner.mode == "b"
    assert changed_settings(s) == {"outer": {"count": 5, "inner": {"mode": "b"}}}
    assert load_settings(_Root) == _Root()
    assert parse_assignment("train.lr=1e-3") == {"train": {"lr": 0.001}}  # YAML 1.1 reads 1e-3 as text


@pytest.mark.parametrize("where, sets, message", [
    (None, ["outer.cuont=3"], "--set outer.cuont=3: unknown setting outer.cuont (known in outer: count, inner)"),
    (None, ["outer.count=0"], "--set outer.count=0: outer.count must be >= 1, got 0"),
    (None, ["outer.inner.mode=c"], "--set outer.inner.mode=c: outer.inner.mode must be one of a, b, got 'c'"),
    (None, ["outer.inner=3"], "--set outer.inner=3: outer.inner must be a mapping of settings, got 3"),
    (None, ["nope"], "--set nope: expected section.key=value"),
    ("outer: {count: x}\n", [], "mine.yaml: outer.count must be a number, got 'x'"),
    ("other: 1\n", [], "mine.yaml: unknown setting other (known: outer)"),
])
def test_loader_names_the_source_and_the_key_in_one_line(tmp_path, where, sets, message):
    f = None
    if where is not None:
        f = tmp_path / "mine.yaml"
        f.write_text(where)
    with pytest.raises(ConfigError) as info:
        load_settings(_Root, f, sets)
    assert message in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize("name, cls", [("lite", TrainConfig), ("dope_dr_50", TrainConfig),
                                       ("dope_dr_400", TrainConfig), ("demo", SynthSettings),
                                       ("procedural", SynthSettings), ("pretrain", SynthSettings)])
def test_a_recipe_holds_only_what_differs_from_the_defaults(name, cls):
    """Every key a packaged recipe states differs from its default (the defaults have one owner)."""
    def leaves(d, prefix=""):
        for k, v in d.items():
            if isinstance(v, dict) and v:
                yield from leaves(v, f"{prefix}{k}.")
            else:
                yield f"{prefix}{k}", v

    recipe = load_config(name)
    changed = dict(leaves(changed_settings(load_settings(cls, name))))
    restated = sorted(k for k, _ in leaves(recipe) if k not in changed)
    assert not restated, f"{name}.yaml restates defaults: {restated}"


def test_the_repository_configs_are_the_packaged_ones():
    """configs/ at the repository root links to the package's configs (one copy)."""
    root = Path(__file__).resolve().parents[1] / "configs"
    assert root.resolve() == CONFIG_DIR.resolve()


def test_synth_settings_are_generated_from_synth_yaml():
    """synth.yaml documents and owns the generator's defaults: the settings classes hold them,
    key for key and value for value, and check each value's kind."""
    assert SynthSettings().to_dict() == load_config("synth")
    assert type(SynthSettings().background.clutter).SECTION == "background.clutter"
    with pytest.raises(ConfigError, match="lights.shadows must be true or false"):
        load_settings(SynthSettings, None, ["lights.shadows=1"])
    with pytest.raises(ConfigError, match=r"target.count has min > max"):
        load_settings(SynthSettings, None, ["target.count=[3,1]"])


def test_inference_options_read_a_file_over_their_defaults(tmp_path):
    f = tmp_path / "track.yaml"
    f.write_text("tracking: {reprojection_px: 2.0}\nmin_score: 0.3\n")
    o = load_settings(InferenceOptions, f)
    assert o.tracking.reprojection_px == 2.0 and o.min_score == 0.3 and o.tracking.max_misses == 15


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dope_hope", *args], capture_output=True, text=True, timeout=120)


def test_settings_command_prints_the_effective_settings():
    r = _cli("settings", "train", "--config", "dope_dr_400", "--set", "train.lr=1e-3")
    assert r.returncode == 0, r.stderr
    printed = yaml.safe_load(r.stdout)
    assert printed["train"]["lr"] == 0.001 and printed["model"]["head"] == 400
    assert TrainConfig.from_mapping(printed) == load_settings(TrainConfig, "dope_dr_400", ["train.lr=1e-3"])
    r = _cli("settings", "infer", "--set", "tracking.reprojection_px=2.0")
    assert r.returncode == 0 and yaml.safe_load(r.stdout)["tracking"]["reprojection_px"] == 2.0


@pytest.mark.parametrize("command", ["synth", "train", "infer", "demo", "bop-submit", "export"])
def test_every_command_with_settings_takes_config_and_set(command):
    """The same --config / --set options, and the same one-line error (exit 2) naming section.key."""
    r = _cli(command, "--help")
    assert "--config" in r.stdout and "--set" in r.stdout
    r = _cli("settings", command, "--set", "nosuch.key=1")
    assert r.returncode == 2 and r.stderr.count("\n") == 1
    assert "--set nosuch.key=1: unknown setting nosuch" in r.stderr


@pytest.mark.parametrize("weights", ["demo_lite.pt", "pretrained_lite.pt"])
def test_the_shipped_checkpoints_recipes_read_as_settings(weights):
    """The recipes the shipped checkpoints recorded (full, as the recipes were when they were
    trained) read as TrainConfig, and lite.yaml (now only what differs) still builds the
    architecture they hold: --init auto starts from the pretrained one."""
    from dope_hope.assets import PRETRAINED_WEIGHTS
    from dope_hope.model.checkpoint import load_checkpoint
    from dope_hope.training.settings import same_architecture

    path = PRETRAINED_WEIGHTS.parent / weights
    if not path.is_file():
        pytest.skip(f"this installation ships no {weights}")
    recorded = load_checkpoint(path)["config"]
    settings = TrainConfig.from_mapping(recorded)
    assert settings.model.arch == "lite" and settings.input.size == (192, 256)
    assert same_architecture(TrainConfig.from_mapping(load_config("lite")), path)


def test_a_set_tracking_key_reaches_the_tracker():
    """`dope-hope infer --track --set tracking.reprojection_px=2.0`: the inference options the
    command builds carry it to each predictor and from there to the stream's tracker."""
    from dope_hope.assets import DEMO_WEIGHTS
    from dope_hope.commands.settings import given_settings
    from dope_hope.inference.model_set import build_predictors
    from dope_hope.inference.tracking import PoseTracker

    if not DEMO_WEIGHTS.is_file():
        pytest.skip("this installation ships no demo model")
    options = given_settings("infer", None, ["tracking.reprojection_px=2.0"])
    (predictor,) = build_predictors([DEMO_WEIGHTS], options=options)
    assert predictor.options.tracking.reprojection_px == 2.0
    assert PoseTracker(predictor).settings.reprojection_px == 2.0
    assert predictor.options.min_score == 0.55  # no min_score given: the model's own
