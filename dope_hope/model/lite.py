"""The ``arch: lite`` network: DOPE's inputs and outputs from a small CPU-trainable body.

Built for training on two CPU cores in ~20 minutes at ~200x200 input. Design (why):

- **Corner identity needs the whole object in view.** A belief peak says *which* of the 8
  corners it is only if the unit sees the object's texture and shape around it (label side,
  cap, long axis); a narrow plain net finds centroids but mixes corners up. So the body is a
  small encoder down to stride 32 (receptive field ~220 px, more than a 200-px image) plus an
  image-level pooled context vector, merged back to the output stride by a top-down
  (FPN-style) path: every output cell sees the full object at a cost of a few MMAC.
- **Refinement sees all keypoints at once.** As in DOPE, stage s > 1 takes
  cat(belief, affinity, features); its dilated 3x3 convs (dilation 1, 2, 4: +112 px of
  context at stride 8) let it enforce a consistent cuboid (corner k sits opposite corner j,
  the affinity field points at the centroid) instead of judging each map alone.
- **Fast convergence on small batches:** BatchNorm after every conv, ReLU; the 1x1 output
  convs start near zero (std 1e-3), so the first steps do not fight random large maps.
- **Cheap:** 3x3 convs only (the fastest kind on CPU), one shared body for belief and
  affinity per stage (official DOPE runs two independent branches).

Stride 8 (``head: 50``) by default, like DOPE-DR-50, so targets/decoding settings carry over;
``head: 100`` gives stride 4 (one more top-down level) for small objects, at ~1.6x the cost.
Numbers (``bench/model_cost.py``, 200x200, one CPU thread): 0.85 M parameters, 0.46 GMAC,
13-28 ms per image (the range is load on the shared machine), vs DOPE-DR-50's 50.3 M
parameters and 38.9 GMAC (~2 s) at the same size.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from dope_hope.errors import ConfigError

NUM_BELIEF = 9
NUM_MAPS = 25
LITE_HEAD_STRIDES = {50: 8, 100: 4}


def conv_bn_relu(cin: int, cout: int, stride: int = 1, dilation: int = 1) -> nn.Sequential:
    """3x3 conv (no bias) -> BatchNorm -> ReLU; 'same' padding for any dilation."""
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, stride=stride, padding=dilation, dilation=dilation, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
    )


def _up_to(x: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    return F.interpolate(x, size=ref.shape[-2:], mode="bilinear", align_corners=False)


class LiteTrunk(nn.Module):
    """Encoder (stride 2..32) + pooled context + top-down merge + ``stages`` refinement stages.

    Args:
        head: 50 (stride 8) or 100 (stride 4).
        stages: refinement stages (1..4), each returning (belief, affinity).
        width: encoder base width w (channels w, 2w, 4w, 4w, 4w at strides 2..32).
        feature_channels: F, width of the merged stride-s features the stages read.
        stage_channels: C, width inside each stage.
        num_objects: N; each stage returns belief (B, 9N, h, w) and affinity (B, 16N, h, w)
            (object k: channels [9k, 9k + 9) and [16k, 16k + 16)); stage s > 1 reads
            cat(belief, affinity, features).
    """

    def __init__(self, head: int = 50, stages: int = 2, width: int = 24,
                 feature_channels: int = 96, stage_channels: int = 64, num_objects: int = 1):
        super().__init__()
        if head not in LITE_HEAD_STRIDES:
            raise ConfigError(f"model.head must be 50 or 100 for arch lite, got {head!r}")
        if not 1 <= stages <= 4:
            raise ConfigError(f"model.stages must be 1..4 for arch lite, got {stages!r}")
        self.stride = LITE_HEAD_STRIDES[head]
        self.num_objects = n = int(num_objects)
        w, fc, sc = int(width), int(feature_channels), int(stage_channels)
        self.stem = nn.Sequential(conv_bn_relu(3, w, 2), conv_bn_relu(w, w))                # /2
        self.down4 = nn.Sequential(conv_bn_relu(w, 2 * w, 2), conv_bn_relu(2 * w, 2 * w))     # /4
        self.down8 = nn.Sequential(conv_bn_relu(2 * w, 4 * w, 2), conv_bn_relu(4 * w, 4 * w))  # /8
        self.down16 = nn.Sequential(conv_bn_relu(4 * w, 4 * w, 2), conv_bn_relu(4 * w, 4 * w, dilation=2))
        self.down32 = nn.Sequential(conv_bn_relu(4 * w, 4 * w, 2), conv_bn_relu(4 * w, 4 * w))
        self.context = nn.Sequential(nn.AdaptiveAvgPool2d(1), nn.Conv2d(4 * w, 4 * w, 1), nn.ReLU(inplace=True))
        self.lat32 = nn.Conv2d(4 * w, fc, 1)
        self.lat16 = nn.Conv2d(4 * w, fc, 1)
        self.lat8 = nn.Conv2d(4 * w, fc, 1)
        self.lat4 = nn.Conv2d(2 * w, fc, 1) if self.stride == 4 else None
        self.merge = conv_bn_relu(fc, fc)
        blocks = []
        for s in range(stages):
            cin = fc if s == 0 else fc + NUM_MAPS * n
            dilations = (1, 2) if s == 0 else (1, 2, 4)
            layers: list[nn.Module] = []
            for d in dilations:
                layers.append(conv_bn_relu(cin, sc, dilation=d))
                cin = sc
            layers.append(nn.Conv2d(sc, NUM_MAPS * n, 1))
            blocks.append(nn.Sequential(*layers))
        self.stages = nn.ModuleList(blocks)

    def reset_output_layers(self) -> None:
        """Near-zero init of each stage's 1x1 output conv (called after the global init)."""
        for block in self.stages:
            nn.init.normal_(block[-1].weight, std=1e-3)
            nn.init.zeros_(block[-1].bias)

    def texture_features(self, x: torch.Tensor) -> torch.Tensor:
        """(N, 3, H, W) -> (N, 2w, H/4, W/4): the encoder's stem and first downsampling."""
        return self.down4(self.stem(x))

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """(N, 3, H, W) -> (N, F, H/stride, W/stride) merged multi-scale features."""
        c4 = self.texture_features(x)
        c8 = self.down8(c4)
        c16 = self.down16(c8)
        c32 = self.down32(c16)
        p = self.lat32(c32 + self.context(c32))
        p = self.lat16(c16) + _up_to(p, c16)
        p = self.lat8(c8) + _up_to(p, c8)
        if self.lat4 is not None:
            p = self.lat4(c4) + _up_to(p, c4)
        return self.merge(p)

    def forward(self, x: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
        feats = self.features(x)
        outputs = []
        inp = feats
        nb = NUM_BELIEF * self.num_objects
        for i, block in enumerate(self.stages):
            maps = block(inp)
            outputs.append((maps[:, :nb], maps[:, nb:]))
            if i + 1 < len(self.stages):
                inp = torch.cat([maps, feats], 1)
        return outputs


def stage_channels_of(state: dict[str, torch.Tensor], prefix: str = "lite.") -> int | None:
    """C, the width inside the stages of a lite state dict (None: no lite stages in it)."""
    first = state.get(f"{prefix}stages.0.0.0.weight")
    return None if first is None else int(first.shape[0])


def stage_count_of(state: dict[str, torch.Tensor], prefix: str = "lite.") -> int:
    """The refinement stages of a lite state dict (0: none)."""
    n = 0
    while f"{prefix}stages.{n}.0.0.weight" in state:
        n += 1
    return n


def deepen_stages(state: dict[str, torch.Tensor], stages: int, prefix: str = "lite.") -> dict[str, torch.Tensor]:
    """A lite state dict of S >= 2 stages -> one of ``stages``: each new stage a copy of the
    last one (stages 2.. all read the features and the previous stage's maps), so the deeper
    network starts by applying the start's last refinement again. ConfigError when
    ``stages`` < S or the start has a single stage (its stage reads the features alone).
    """
    old = stage_count_of(state, prefix)
    stages = int(stages)
    if old < 2 or stages < old:
        raise ConfigError(f"model.stages {stages}: a start of {old} stage(s) can be deepened only from "
                          "two stages or more, and not made shallower")
    out = dict(state)
    last = f"{prefix}stages.{old - 1}."
    for k in range(old, stages):
        for key, value in state.items():
            if key.startswith(last):
                out[f"{prefix}stages.{k}." + key[len(last):]] = value.clone()
    return out


def widen_stage_channels(state: dict[str, torch.Tensor], channels: int, prefix: str = "lite.",
                         seed: int = 0) -> dict[str, torch.Tensor]:
    """A lite state dict whose stages are C wide -> the same network with stages ``channels``
    wide, computing the same maps.

    Each stage's 3x3 convs get ``channels - C`` new output channels (He-normal, fan-out, from a
    generator seeded with ``seed``: reproducible) with identity BatchNorm; the old channels
    read none of the new ones (those input weights start at zero) and the 1x1 output conv reads
    none of them either, so every map equals the narrow network's at the start, while each new
    weight has a gradient from the first step. ConfigError when ``channels`` < C.
    """
    old = stage_channels_of(state, prefix)
    if old is None:
        raise ConfigError("widen_stage_channels: not a lite state dict (no stages)")
    channels = int(channels)
    if channels < old:
        raise ConfigError(f"model.lite.stage_channels {channels} is narrower than the start's {old}: "
                          "a start can be widened, not narrowed")
    out = dict(state)
    if channels == old:
        return out
    extra = channels - old
    gen = torch.Generator().manual_seed(int(seed))
    for stage in range(stage_count_of(state, prefix)):
        layer = 0
        while f"{prefix}stages.{stage}.{layer}.0.weight" in state:
            key = f"{prefix}stages.{stage}.{layer}"
            w = state[f"{key}.0.weight"]
            cin = w.shape[1] if layer == 0 else channels
            fan_out = channels * w.shape[2] * w.shape[3]
            new = torch.randn((channels, cin) + tuple(w.shape[2:]), generator=gen, dtype=w.dtype) \
                * (2.0 / fan_out) ** 0.5
            new[:old, :w.shape[1]] = w
            if layer > 0:
                new[:old, old:] = 0.0  # the old channels read none of the new ones
            out[f"{key}.0.weight"] = new
            for name, fill in (("weight", 1.0), ("bias", 0.0), ("running_mean", 0.0), ("running_var", 1.0)):
                v = state[f"{key}.1.{name}"]
                out[f"{key}.1.{name}"] = torch.cat([v, torch.full((extra,), fill, dtype=v.dtype)])
            layer += 1
        w = state[f"{prefix}stages.{stage}.{layer}.weight"]  # the 1x1 output conv
        out[f"{prefix}stages.{stage}.{layer}.weight"] = torch.cat(
            [w, torch.zeros((w.shape[0], extra) + tuple(w.shape[2:]), dtype=w.dtype)], 1)
    return out
