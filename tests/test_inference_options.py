"""dope_hope.inference.options: the packaged defaults load, every key is checked."""
from __future__ import annotations

import pytest

from dope_hope.config import load_config
from dope_hope.errors import ConfigError
from dope_hope.inference.options import InferenceOptions, preset_options
from dope_hope.refine.line_search import LineSearchSettings


def test_packaged_defaults():
    o = InferenceOptions.from_mapping()
    assert o.height is None and o.pose_search == "hypotheses" and o.min_score == 0.5
    assert o.icp is False and o.ls_points == 1000 and o.line_search == LineSearchSettings()


def test_infer_yaml_gives_the_top_level_defaults_and_leaves_the_stages_to_their_classes():
    """One owner per default: configs/infer.yaml's top-level keys are InferenceOptions' defaults
    (read from it), its stage sections are empty (the stage classes own theirs)."""
    packaged = load_config("infer")
    defaults = InferenceOptions().to_dict()
    for key, value in packaged.items():
        if isinstance(value, dict):
            assert value == {}, key
        else:
            assert defaults[key] == value, key
    assert set(packaged) == set(defaults)


def test_overrides_and_stage_keywords_are_accepted():
    o = InferenceOptions.from_mapping({"height": 240, "icp": True,
                                       "line_search": {"search": [0.7, 1.4]}, "pnp": {"min_points": 6},
                                       "hypotheses": {"max_hypotheses": 50}, "decode": {"threshold": 0.2}})
    assert o.height == 240 and o.icp and o.line_search.search == (0.7, 1.4)


@pytest.mark.parametrize("overrides, message", [
    ({"hieght": 240}, "unknown setting hieght (known: "),
    ({"line_search": {"serach": [0.7, 1.4]}}, "unknown setting line_search.serach (known in line_search: "),
    ({"pnp": {"K": 1}}, "unknown setting pnp.K"),
    ({"height": 5}, "height must be a whole number of pixels in 8..4096"),
    ({"min_score": float("nan")}, "min_score must be a finite number"),
    ({"pose_search": "brute"}, "pose_search must be one of hypotheses, groups"),
    ({"icp": "yes"}, "icp must be true, false or auto, got 'yes'"),
    ({"ls_points": 10.5}, "ls_points must be a whole number, got 10.5"),
    ({"icp_points": 9}, "icp_points must be >= 10, got 9"),
    ({"ls_points": True}, "ls_points must be a number, got True"),
])
def test_mistakes_are_refused_in_one_line(overrides, message):
    with pytest.raises(ConfigError) as exc:
        InferenceOptions.from_mapping(overrides)
    assert message in str(exc.value) and "\n" not in str(exc.value)


def test_whole_numbers_follow_the_config_rule():
    """The one number rule (config.whole_number): 10.0 counts as 10, as it does in a config."""
    o = InferenceOptions.from_mapping({"ls_points": 10.0, "icp_points": 12})
    assert o.ls_points == 10 and isinstance(o.ls_points, int) and o.icp_points == 12


def test_presets_put_what_is_given_on_top_and_fit_the_model():
    """"fast" is the packaged defaults; "accurate" its packaged file (three sizes, ICP where it
    can run, the turns), under what a user sets; a fixed-size export keeps one size, a new
    object's detector its own sizes and turns."""
    assert preset_options("fast") == {} and preset_options("fast", {"icp": True}) == {"icp": True}
    accurate = preset_options("accurate")
    assert accurate == load_config("infer_accurate")
    o = InferenceOptions.from_mapping(accurate)
    assert o.icp == "auto" and o.multiscale.scales == (1.0, 0.75, 1.33) and o.appearance.trained_turns
    given = preset_options("accurate", {"icp": False, "multiscale": {"duplicate_iou": 0.3}})
    o = InferenceOptions.from_mapping(given)
    assert o.icp is False and o.multiscale.scales == (1.0, 0.75, 1.33) and o.multiscale.duplicate_iou == 0.3
    assert "multiscale" not in preset_options("accurate", fixed_size=True)
    assert preset_options("accurate", {"multiscale": {"scales": [1.0]}}, fixed_size=True)["multiscale"] == {"scales": [1.0]}
    assert preset_options("accurate", meshes=False)["appearance"] == {}  # no mesh: no turns to warn of
    new = preset_options("accurate", new_object=True)
    assert new == {"icp": "auto", "appearance": {}}
    assert load_config("infer_accurate")["appearance"] == {"trained_turns": True}  # the file is not changed
    with pytest.raises(ConfigError, match="preset: one of fast, accurate, got 'best'"):
        preset_options("best")


def test_infer_reads_each_setting_once_and_builds_a_predictors_options_once(tmp_path, monkeypatch, capsys):
    """`infer --set` on one model: the item is parsed once; InferenceOptions is built for the
    defaults and the --set layer as the loader checks them, then once by the predictor (and
    copied once to take the model's own threshold), which runs with the value given."""
    import json

    import cv2
    import numpy as np

    import dope_hope.config as config
    from dope_hope.cli import main
    from dope_hope.inference.predictor import DopePredictor

    image = tmp_path / "frame.png"
    cv2.imwrite(str(image), np.zeros((64, 80, 3), np.uint8))
    (tmp_path / "frame.json").write_text(json.dumps({"camera_data": {
        "intrinsics": {"fx": 60.0, "fy": 60.0, "cx": 40.0, "cy": 32.0}, "width": 80, "height": 64}, "objects": []}))
    parsed, built, used = [], [], []
    real_parse, real_post = config.parse_assignment, InferenceOptions.__post_init__
    monkeypatch.setattr(config, "parse_assignment", lambda item: parsed.append(item) or real_parse(item))
    monkeypatch.setattr(InferenceOptions, "__post_init__", lambda self: built.append(1) or real_post(self))
    real_detect = DopePredictor.detect_image
    monkeypatch.setattr(DopePredictor, "detect_image",
                        lambda self, *a, **k: used.append(self.options) or real_detect(self, *a, **k))
    assert main(["infer", str(image), "--set", "decode.threshold=0.2", "--out", str(tmp_path / "out"),
                 "--no-progress", "--no-overlay", "--fast"]) == 0
    assert parsed == ["decode.threshold=0.2"]
    assert len(built) == 4  # defaults, the --set layer; the predictor's, its copy with the model's min_score
    assert [o.decode.threshold for o in used] == [0.2] and used[0].min_score == 0.55  # the demo model's own
