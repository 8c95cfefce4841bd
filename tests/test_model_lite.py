"""The lite network's stages widened from a narrower start (``model.lite.widen_stage_channels``):
the wider network computes the start's maps exactly, its new weights learn from the first step,
the widening is reproducible, and a start is never narrowed. ``--init`` applies it
(``training.init_weights.load_init_weights``) when ``model.lite.stage_channels`` exceeds the start's;
likewise more ``model.stages`` than the start's (``model.lite.deepen_stages``)."""
from __future__ import annotations

import pytest
import torch

from dope_hope.errors import ConfigError
from dope_hope.model.lite import deepen_stages, stage_channels_of, stage_count_of, widen_stage_channels
from dope_hope.model.network import build_model

torch.set_num_threads(1)


def _lite(stage_channels: int, objects: int = 1, head: int = 50, stages: int = 2) -> torch.nn.Module:
    return build_model({"arch": "lite", "head": head, "stages": stages, "num_objects": objects,
                        "lite": {"width": 8, "feature_channels": 16, "stage_channels": stage_channels}},
                       load_backbone=False)


def _trained_looking(model: torch.nn.Module) -> torch.nn.Module:
    """BatchNorm statistics and output convs away from their initial values (so an identity
    that holds only at initialisation would show)."""
    gen = torch.Generator().manual_seed(1)
    for m in model.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.copy_(torch.rand(m.num_features, generator=gen) - 0.5)
            m.running_var.copy_(0.5 + torch.rand(m.num_features, generator=gen))
            m.weight.data.copy_(0.5 + torch.rand(m.num_features, generator=gen))
        elif isinstance(m, torch.nn.Conv2d) and m.kernel_size == (1, 1):
            m.weight.data.normal_(0.0, 0.2, generator=gen)
    return model.eval()


@pytest.mark.parametrize("objects,head,stages", [(1, 50, 2), (3, 100, 2), (2, 50, 3)])
def test_the_widened_stages_compute_the_start_s_maps(objects, head, stages):
    narrow = _trained_looking(_lite(16, objects, head, stages))
    wide = _lite(24, objects, head, stages).eval()
    state = widen_stage_channels(narrow.state_dict(), 24)
    wide.load_state_dict(state, strict=True)
    assert stage_channels_of(state) == 24 and stage_channels_of(narrow.state_dict()) == 16
    x = torch.rand(2, 3, 64, 80)
    with torch.no_grad():
        for (b0, a0), (b1, a1) in zip(narrow(x), wide(x)):
            assert b0.abs().max() > 0.1  # the maps are not trivially zero
            torch.testing.assert_close(b1, b0, atol=1e-5, rtol=1e-5)
            torch.testing.assert_close(a1, a0, atol=1e-5, rtol=1e-5)


def test_the_new_channels_learn_from_the_first_step_and_the_widening_is_reproducible():
    narrow = _trained_looking(_lite(16))
    state = widen_stage_channels(narrow.state_dict(), 24)
    again = widen_stage_channels(narrow.state_dict(), 24)
    assert all(torch.equal(state[k], again[k]) for k in state)
    assert not torch.equal(state["lite.stages.0.0.0.weight"], widen_stage_channels(narrow.state_dict(), 24, seed=1)
                           ["lite.stages.0.0.0.weight"])
    wide = _lite(24)
    wide.load_state_dict(state)
    wide.train()
    belief, affinity = wide(torch.rand(2, 3, 64, 64))[-1]
    (belief.square().mean() + affinity.square().mean()).backward()
    out = wide.lite.stages[-1][-1].weight.grad  # the output conv's zero columns of the new channels
    assert out[:, 16:].abs().sum() > 0
    inner = wide.lite.stages[-1][1][0].weight.grad  # old channels reading the new ones (zero at start)
    assert inner[:16, 16:].abs().sum() > 0


def test_a_start_is_widened_not_narrowed():
    state = _lite(16).state_dict()
    with pytest.raises(ConfigError, match="narrower than the start's 16"):
        widen_stage_channels(state, 8)
    same = widen_stage_channels(state, 16)
    assert all(same[k] is state[k] for k in state)
    with pytest.raises(ConfigError, match="not a lite state dict"):
        widen_stage_channels({"x": torch.zeros(1)}, 16)


def test_init_from_the_shipped_start_widens_objects_and_stages():
    from dope_hope.assets import PRETRAINED_WEIGHTS
    from dope_hope.config import load_config
    from dope_hope.training.init_weights import load_init_weights
    from dope_hope.training.objects import with_num_objects
    from dope_hope.training.settings import TrainConfig

    if not PRETRAINED_WEIGHTS.is_file():
        pytest.skip("this installation ships no pretrained start")
    config = with_num_objects(TrainConfig.from_mapping(load_config("lite")), 2).to_dict()
    narrow = build_model(config, load_backbone=False).eval()
    load_init_weights(narrow, PRETRAINED_WEIGHTS)
    width = stage_channels_of(narrow.state_dict())
    wide_config = {**config, "model": {**config["model"], "lite": {**config["model"].get("lite", {}),
                                                                   "stage_channels": width + 32}}}
    wide = build_model(wide_config, load_backbone=False).eval()
    load_init_weights(wide, PRETRAINED_WEIGHTS)
    assert stage_channels_of(wide.state_dict()) == width + 32
    x = torch.rand(1, 3, 64, 64)
    with torch.no_grad():
        torch.testing.assert_close(wide(x)[-1][0], narrow(x)[-1][0], atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("objects", [1, 2])
def test_deepened_stages_apply_the_start_s_last_stage_again(objects):
    shallow = _trained_looking(_lite(16, objects, stages=2))
    deep = _lite(16, objects, stages=4).eval()
    state = deepen_stages(shallow.state_dict(), 4)
    deep.load_state_dict(state, strict=True)
    assert stage_count_of(state) == 4 and stage_count_of(shallow.state_dict()) == 2
    x = torch.rand(2, 3, 64, 80)
    with torch.no_grad():
        start, deeper = shallow(x), deep(x)
        for (b0, a0), (b1, a1) in zip(start, deeper[:2]):  # the start's stages unchanged
            torch.testing.assert_close(b1, b0)
            torch.testing.assert_close(a1, a0)
        feats = shallow.lite.features(x)
        again = shallow.lite.stages[-1](torch.cat([*start[-1], feats], 1))  # the last stage once more
        nb = 9 * objects
        torch.testing.assert_close(deeper[2][0], again[:, :nb])
        torch.testing.assert_close(deeper[2][1], again[:, nb:])
    state["lite.stages.3.0.0.weight"].add_(1.0)  # copies, not views of the start's tensors
    assert not torch.equal(state["lite.stages.3.0.0.weight"], state["lite.stages.2.0.0.weight"])


def test_a_start_is_deepened_from_two_stages_and_never_made_shallower():
    with pytest.raises(ConfigError, match="not made shallower"):
        deepen_stages(_lite(16, stages=3).state_dict(), 2)
    with pytest.raises(ConfigError, match="from two stages or more"):
        deepen_stages(_lite(16, stages=1).state_dict(), 3)
    from dope_hope.assets import PRETRAINED_WEIGHTS
    from dope_hope.config import load_config
    from dope_hope.training.init_weights import load_init_weights

    if not PRETRAINED_WEIGHTS.is_file():
        pytest.skip("this installation ships no pretrained start")
    config = load_config("lite")
    deep = build_model({**config, "model": {**config["model"], "stages": 3}}, load_backbone=False)
    load_init_weights(deep, PRETRAINED_WEIGHTS)  # --init pretrained with model.stages=3
    assert stage_count_of(deep.state_dict()) == 3
    assert torch.equal(deep.lite.stages[2][0][0].weight, deep.lite.stages[1][0][0].weight)
