"""The ROS 2 node's parameters (dope_hope/ros/node_params.py): the inference settings under
their --set names, the node's own, the values that change at run time. No ROS needed."""
from __future__ import annotations

import pytest

from dope_hope.errors import ConfigError
from dope_hope.ros.node_params import (
    NodeSettings,
    checked_classes,
    checked_min_score,
    given_inference_settings,
    inference_parameter_names,
    node_parameter_names,
)


def test_every_inference_setting_is_a_parameter_under_its_set_name():
    names = inference_parameter_names()
    assert names["min_score"] == 0.5 and "decode.threshold" in names and "line_search.search" in names
    assert not set(names) & set(node_parameter_names())


def test_given_parameters_nest_as_a_settings_file_over_the_command_settings():
    given = given_inference_settings({"decode.threshold": 0.2, "line_search.search": [0.9, 1.1],
                                      "height": "null", "icp": True}, base={"decode": {"nms_radius": 2}})
    assert given == {"decode": {"threshold": 0.2, "nms_radius": 2}, "line_search": {"search": [0.9, 1.1]},
                     "height": None, "icp": True}


@pytest.mark.parametrize("values, message", [
    ({"decode.threshold": "high"}, "decode.threshold"),
    ({"decode.nope": 1.0}, "unknown setting decode.nope"),
    ({"icp": 1}, "icp must be true, false or auto"),
])
def test_a_bad_inference_parameter_is_named(values, message):
    with pytest.raises(ConfigError, match=message):
        given_inference_settings(values)


def test_node_settings_check_their_values():
    s = NodeSettings.from_mapping({"weights": "a.pt", "mesh": ["Ketchup=k.obj"], "threads": 2})
    assert s.weights == ("a.pt",) and s.mesh == ("Ketchup=k.obj",) and s.threads == 2
    with pytest.raises(ConfigError, match="image_transport must be one of raw, compressed"):
        NodeSettings.from_mapping({"image_transport": "theora"})
    with pytest.raises(ConfigError, match="input_reliability must be one of best_effort, reliable"):
        NodeSettings.from_mapping({"input_reliability": "sometimes"})
    with pytest.raises(ConfigError, match="depth_tolerance_ms must be > 0"):
        NodeSettings.from_mapping({"depth_tolerance_ms": -1.0})


def test_runtime_values_are_checked():
    assert checked_min_score(0.3) == 0.3 and checked_min_score(None) is None
    for bad in ("0.3", True, float("nan")):
        with pytest.raises(ConfigError, match="min_score"):
            checked_min_score(bad)
    assert checked_classes(["demobox"], ["DemoBox", "Ketchup"]) == ("DemoBox",)
    assert checked_classes([], ["DemoBox"]) is None
    with pytest.raises(ConfigError, match="'Mustard' is not an object this node detects"):
        checked_classes(["Mustard"], ["DemoBox"])
