"""DopeNetwork: output shapes per head, the official DOPE parameter layout, lite, normalization."""
from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from dope_hope.config import load_config
from dope_hope.errors import ConfigError, ModelFileError
from dope_hope.model import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    build_model,
    load_backbone_weights,
    normalize_batch,
    normalize_image,
)

torch.set_num_threads(1)

# The official DOPE layout (NVlabs/Deep_Object_Pose, class DopeNetwork), written out from the
# published architecture, independently of dope_hope.model: (name, in, out, kernel) per conv.
_VGG19_CONVS = [(0, 3, 64), (2, 64, 64), (5, 64, 128), (7, 128, 128), (10, 128, 256),
                (12, 256, 256), (14, 256, 256), (16, 256, 256), (19, 256, 512), (21, 512, 512),
                (23, 512, 256), (25, 256, 128)]


def official_layout() -> list[tuple[str, int, int, int]]:
    convs = [(f"vgg.{i}", cin, cout, 3) for i, cin, cout in _VGG19_CONVS]
    for s in range(1, 7):
        for branch, out in (("2", 9), ("1", 16)):  # _2 belief, _1 affinity
            name = f"m{s}_{branch}"
            if s == 1:
                convs += [(f"{name}.0", 128, 128, 3), (f"{name}.2", 128, 128, 3),
                          (f"{name}.4", 128, 128, 3), (f"{name}.6", 128, 512, 1),
                          (f"{name}.8", 512, out, 1)]
            else:
                convs += [(f"{name}.0", 153, 128, 7)]
                convs += [(f"{name}.{i}", 128, 128, 7) for i in (2, 4, 6, 8)]
                convs += [(f"{name}.10", 128, 128, 1), (f"{name}.12", 128, out, 1)]
    return convs


def official_state_dict(prefix: str = "") -> dict[str, torch.Tensor]:
    """A state dict with the official names and shapes; every tensor a distinct constant."""
    state = {}
    for n, (name, cin, cout, k) in enumerate(official_layout()):
        state[f"{prefix}{name}.weight"] = torch.full((cout, cin, k, k), 0.001 * n)
        state[f"{prefix}{name}.bias"] = torch.full((cout,), -0.001 * n)
    return state


@pytest.fixture(scope="module")
def dr50():
    return build_model(load_config("dope_dr_50")).eval()


def test_dr50_maps_400_input_to_six_stages_at_stride_8(dr50):
    assert dr50.stride == 8
    with torch.no_grad():
        out = dr50(torch.randn(1, 3, 400, 400))
    assert len(out) == 6
    for belief, affinity in out:
        assert belief.shape == (1, 9, 50, 50)
        assert affinity.shape == (1, 16, 50, 50)


def test_official_state_dict_loads_strict(dr50):
    state = official_state_dict()
    assert len(state) == 2 * (12 + 2 * 5 + 10 * 7)  # trunk 12 convs; stage 1: 2x5; 2-6: 10x7
    result = dr50.load_state_dict(state, strict=True)
    assert not result.missing_keys and not result.unexpected_keys
    own = dr50.state_dict()
    assert torch.equal(own["m6_1.12.weight"], state["m6_1.12.weight"])
    assert torch.equal(own["vgg.25.bias"], state["vgg.25.bias"])


def test_dr400_shapes_and_untrained_decoder_is_bilinear_upsampling(dr50):
    dr400 = build_model(load_config("dope_dr_400")).eval()
    assert dr400.stride == 1
    # the 50-px part of a 400 model takes official weights; only decoder keys are missing
    result = dr400.load_state_dict(dr50.state_dict(), strict=False)
    assert result.unexpected_keys == []
    assert result.missing_keys and all(k.startswith("decoder.") for k in result.missing_keys)
    x = torch.randn(1, 3, 64, 48)
    with torch.no_grad():
        coarse = dr50(x)
        fine = dr400(x)
    assert len(fine) == 6
    for (b50, a50), (b, a) in zip(coarse, fine):
        assert b.shape == (1, 9, 64, 48) and a.shape == (1, 16, 64, 48)
        # a fresh decoder starts as the bilinear x8 upsampling of the 50-px maps
        expected = F.interpolate(b50, scale_factor=8, mode="bilinear", align_corners=False)
        torch.testing.assert_close(b, expected, atol=1e-5, rtol=1e-4)
    with torch.no_grad():
        b, a = dr400(torch.randn(1, 3, 400, 400))[-1]
    assert b.shape == (1, 9, 400, 400) and a.shape == (1, 16, 400, 400)


def test_decoder_is_trainable_and_small(dr50):
    dr400 = build_model({"arch": "dope", "head": 400, "stages": 1})
    b, a = dr400(torch.randn(1, 3, 32, 32))[-1]
    (b.square().mean() + a.square().mean()).backward()
    assert dr400.decoder.out.weight.grad.abs().sum() > 0
    n_decoder = sum(p.numel() for p in dr400.decoder.parameters())
    n_trunk = sum(p.numel() for p in dr400.vgg.parameters())
    assert n_decoder < 0.05 * n_trunk


def test_lite_shapes_and_size():
    model = build_model(load_config("lite"))
    n = sum(p.numel() for p in model.parameters())
    assert 0.3e6 <= n <= 1.5e6
    assert model.stride == 4  # configs/lite.yaml: head 100
    model.train()
    out = model(torch.randn(2, 3, 200, 200))
    assert len(out) == load_config("lite")["model"]["stages"]
    for belief, affinity in out:
        assert belief.shape == (2, 9, 50, 50) and affinity.shape == (2, 16, 50, 50)
    sum(b.mean() + a.mean() for b, a in out).backward()
    assert all(p.grad is not None for p in model.parameters())
    # lite weights are not DOPE weights: no name in common with the official layout
    assert not set(model.state_dict()) & set(official_state_dict())

    coarse = build_model({"arch": "lite", "head": 50, "stages": 1}).eval()
    with torch.no_grad():
        b, a = coarse(torch.randn(1, 3, 96, 64))[0]
    assert coarse.stride == 8 and b.shape == (1, 9, 12, 8) and a.shape == (1, 16, 12, 8)


def test_texture_features_are_the_first_layers_at_stride_4(dr50):
    """What the appearance check compares renders by: the lite stem and first downsampling,
    VGG19's first two blocks; the same numbers as running those layers by hand."""
    x = torch.randn(2, 3, 64, 48)
    lite = build_model(load_config("lite")).eval()
    with torch.no_grad():
        f_lite, f_dope = lite.texture_features(x), dr50.texture_features(x)
        by_hand = lite.lite.down4(lite.lite.stem(x))
        vgg = dr50.vgg[4](dr50.vgg[3](dr50.vgg[2](dr50.vgg[1](dr50.vgg[0](x)))))
        vgg = dr50.vgg[9](dr50.vgg[8](dr50.vgg[7](dr50.vgg[6](dr50.vgg[5](vgg)))))
    assert f_lite.shape == (2, 48, 16, 12)  # twice the encoder width (24)
    assert f_dope.shape == (2, 128, 16, 12)
    torch.testing.assert_close(f_lite, by_hand)
    torch.testing.assert_close(f_dope, vgg)


def test_build_model_rejects_bad_configs():
    with pytest.raises(ConfigError, match="arch"):
        build_model({"arch": "resnet"})
    with pytest.raises(ConfigError, match="head"):
        build_model({"arch": "dope", "head": 100})
    with pytest.raises(ConfigError, match="stagez"):
        build_model({"arch": "lite", "stagez": 2})
    with pytest.raises(ConfigError, match="unknown setting model.lite.depth"):
        build_model({"arch": "lite", "lite": {"depth": 3}})


def test_normalize_image_and_batch_agree():
    rgb = np.zeros((4, 5, 3), np.uint8)
    rgb[..., 0] = 255
    rgb[1, 2] = (10, 20, 30)
    x = normalize_image(rgb)
    assert x.shape == (3, 4, 5) and x.dtype == torch.float32
    assert x[0, 0, 0].item() == pytest.approx((1.0 - IMAGENET_MEAN[0]) / IMAGENET_STD[0])
    assert x[2, 1, 2].item() == pytest.approx((30 / 255 - IMAGENET_MEAN[2]) / IMAGENET_STD[2])
    batch = torch.from_numpy(rgb).permute(2, 0, 1)[None]
    torch.testing.assert_close(normalize_batch(batch)[0], x)
    torch.testing.assert_close(normalize_batch(batch.float() / 255)[0], x)
    from dope_hope.preprocess import denormalize_rgb  # the snapshots' way back to pixels
    np.testing.assert_array_equal(denormalize_rgb(x.numpy()), rgb)


def test_load_backbone_weights_maps_torchvision_keys(tmp_path, dr50):
    from torchvision.models.vgg import cfgs, make_layers

    features = make_layers(cfgs["E"])  # the layer table of torchvision.models.vgg19
    for i, p in enumerate(features.parameters()):
        p.data.fill_(0.5 + i)
    state = {f"features.{k}": v for k, v in features.state_dict().items()}
    state["classifier.0.weight"] = torch.zeros(2, 2)
    path = tmp_path / "vgg19.pth"
    torch.save(state, path)
    loaded = load_backbone_weights(dr50, path)
    assert len(loaded) == 20 and loaded[0] == "vgg.0.weight" and loaded[-1] == "vgg.21.bias"
    assert torch.equal(dr50.vgg[21].weight, features[21].weight)
    # the config route: model.backbone_weights names the local file
    small = build_model({"arch": "dope", "head": 50, "stages": 1, "backbone_weights": str(path)})
    assert torch.equal(small.vgg[0].bias, features[0].bias)
    bad = tmp_path / "not_vgg.pth"
    torch.save({"features.0.weight": torch.zeros(1)}, bad)
    with pytest.raises(ModelFileError, match="not_vgg.pth"):
        load_backbone_weights(dr50, bad)


def test_official_file_with_module_prefix_imports(tmp_path):
    from dope_hope.model.checkpoint import import_official, load_model

    state = official_state_dict(prefix="module.")  # as saved from DataParallel / DDP
    pth = tmp_path / "Ketchup.pth"
    torch.save(state, pth)
    out = tmp_path / "ketchup_ckpt.pth"
    ckpt = import_official(pth, "Ketchup", out_path=out)
    assert set(ckpt["model"]) == {k.removeprefix("module.") for k in state}
    model, _ = load_model(out)
    assert torch.equal(model.m3_2[8].weight, state["module.m3_2.8.weight"])
    assert torch.equal(model.vgg[0].bias, state["module.vgg.0.bias"])
