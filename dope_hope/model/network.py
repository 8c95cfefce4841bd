"""DopeNetwork: VGG19 trunk + six two-branch refinement stages, with a 50-px or 400-px head.

Input: ImageNet-normalized RGB, (B, 3, H, W) float32 with H, W divisible by 8. Output: a list
with one ``(belief (B, 9N, h, w), affinity (B, 16N, h, w))`` pair per stage (deep supervision)
for a model of N objects (``model.num_objects``, default 1): object k owns belief channels
[9k, 9k + 9) and affinity channels [16k, 16k + 16); N = 1 is the official layout.
``h, w = dope_hope.maps.grid.map_size((H, W), model.stride)``. :func:`widen_to_objects` turns
a one-object state dict into an N-object one whose every group starts as the one object's.

Parameter names follow the official DOPE checkpoints (NVlabs/Deep_Object_Pose, class
``DopeNetwork``), so an official ``.pth`` loads with ``strict=True``:

- ``vgg.<i>``: torchvision ``vgg19().features[0..22]`` (through conv4_2 + ReLU, stride 8),
  then ``vgg.23`` conv 512->256 3x3, ``vgg.24`` ReLU, ``vgg.25`` conv 256->128 3x3,
  ``vgg.26`` ReLU. Convs sit at 0 2 5 7 10 12 14 16 19 21 23 25.
- ``m<s>_2`` (belief, 9 maps) and ``m<s>_1`` (affinity, 16 fields), ``s = 1..6``: an
  ``nn.Sequential`` with ReLUs interleaved, convs at even indices. Stage 1 (input 128 ch):
  0 2 4 = 3x3 convs to 128, 6 = 1x1 128->512, 8 = 1x1 512->out. Stages 2-6 (input
  cat(belief, affinity, features) = 9 + 16 + 128 = 153 ch): 0 2 4 6 8 = 7x7 convs to 128
  (pad 3), 10 = 1x1 128->128, 12 = 1x1 128->out. No ReLU after the last conv.

Head 400 (DOPE-DR-400) adds :class:`UpsamplingDecoder` under the name ``decoder.*`` (no clash
with official names, so the 50-px part loads official weights with ``strict=False`` and only
``decoder.*`` keys missing); ``bench/model_cost.py`` measures what it costs beside the trunk
(figures in bench/RESULTS.md). ``decoder.stages: last`` decodes only the last stage
(the others are bilinear-upsampled), e.g. for inference, where only ``outputs[-1]`` is used.
The ``arch: lite`` variant lives in :mod:`dope_hope.model.lite`.
"""
from __future__ import annotations

import inspect
import os
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn
from torchvision.models.vgg import cfgs as _vgg_cfgs
from torchvision.models.vgg import make_layers as _vgg_make_layers

from dope_hope.config import load_config
from dope_hope.errors import ConfigError, DopeHopeError, ModelFileError
from dope_hope.io.paths import require_file
from dope_hope.model.lite import LiteTrunk
from dope_hope.model.settings import ModelSettings
from dope_hope.preprocess import IMAGENET_MEAN, IMAGENET_STD, normalize_rgb

NUM_BELIEF = 9
NUM_AFFINITY = 16
NUM_MAPS = NUM_BELIEF + NUM_AFFINITY
#: Trunk output channels of the official network.
FEATURE_CHANNELS = 128
#: Number of ``vgg19().features`` layers kept: through conv4_2 + ReLU (index 22), stride 8.
VGG_LAYERS_KEPT = 23
#: VGG19's layers up to its second pooling (stride 4): conv1_1 ... conv2_2 and the two pools.
VGG_STRIDE4_LAYERS = 10
#: Head name -> map stride (image pixels per map cell).
HEAD_STRIDES = {50: 8, 400: 1}


# ----------------------------------------------------------------------------- normalization
def normalize_image(rgb: np.ndarray, mean=IMAGENET_MEAN, std=IMAGENET_STD) -> torch.Tensor:
    """(H, W, 3) uint8 RGB -> (3, H, W) float32 tensor (:func:`dope_hope.preprocess.normalize_rgb`)."""
    return torch.from_numpy(normalize_rgb(rgb, mean, std))


def normalize_batch(images: torch.Tensor, mean=IMAGENET_MEAN, std=IMAGENET_STD) -> torch.Tensor:
    """(N, 3, H, W) RGB -> normalized float32 (same device).

    uint8 input is divided by 255; floating input is taken to be in [0, 1] already.
    """
    if images.ndim != 4 or images.shape[1] != 3:
        raise ValueError(f"expected an (N, 3, H, W) batch, got shape {tuple(images.shape)}")
    x = images.float()
    if images.dtype == torch.uint8:
        x = x / 255.0
    m = torch.tensor(mean, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
    s = torch.tensor(std, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
    return (x - m) / s


# ----------------------------------------------------------------------------- building blocks
def vgg_trunk() -> nn.Sequential:
    """The official trunk: vgg19 features[0..22] then conv 512->256, ReLU, conv 256->128, ReLU.

    Built from torchvision's VGG19 layer table with no weights (nothing is downloaded).
    """
    features = _vgg_make_layers(_vgg_cfgs["E"], batch_norm=False)
    layers = list(features.children())[:VGG_LAYERS_KEPT]
    layers += [
        nn.Conv2d(512, 256, kernel_size=3, padding=1), nn.ReLU(inplace=True),
        nn.Conv2d(256, FEATURE_CHANNELS, kernel_size=3, padding=1), nn.ReLU(inplace=True),
    ]
    return nn.Sequential(*layers)


def dope_stage(in_channels: int, out_channels: int, first: bool) -> nn.Sequential:
    """One official stage branch (convs at even indices, ReLUs between, none at the end)."""
    kernel, pad, n_spatial, penultimate = (3, 1, 3, 512) if first else (7, 3, 5, 128)
    mid = 128
    layers: list[nn.Module] = [nn.Conv2d(in_channels, mid, kernel, padding=pad)]
    for _ in range(n_spatial - 1):
        layers += [nn.ReLU(inplace=True), nn.Conv2d(mid, mid, kernel, padding=pad)]
    layers += [nn.ReLU(inplace=True), nn.Conv2d(mid, penultimate, 1)]
    layers += [nn.ReLU(inplace=True), nn.Conv2d(penultimate, out_channels, 1)]
    return nn.Sequential(*layers)


class UpsamplingDecoder(nn.Module):
    """Learned x8 upsampling of stage maps to full input resolution (DOPE-DR-400 head).

    Per stage: ``cat(maps (25), reduce(features) (r))`` at stride 8 -> three stride-2
    transposed convs (4x4, ReLU) -> 1x1 conv to 25 channels, added to the bilinear x8
    upsampling of the stage's maps. The last conv starts at zero, so an untrained decoder
    returns exactly the bilinearly upsampled 50-px maps (an imported official model works
    at once and fine-tunes from there). The feature reduction runs once, not per stage.

    Bilinear with ``align_corners=False`` puts map cell j's centre at image ``8j + 3.5``,
    the convention of :mod:`dope_hope.maps.grid`.
    """

    def __init__(self, feature_channels: int = FEATURE_CHANNELS, reduce_channels: int = 32,
                 channels: tuple[int, ...] = (32, 16, 16), decode_stages: str = "all", num_objects: int = 1):
        super().__init__()
        self.num_objects = int(num_objects)
        maps_channels = NUM_MAPS * self.num_objects
        if len(channels) != 3:
            raise ConfigError(f"model.decoder.channels must list 3 widths (x2 each), got {channels}")
        if decode_stages not in ("all", "last"):
            raise ConfigError(f"model.decoder.stages must be 'all' or 'last', got {decode_stages!r}")
        self.decode_stages = decode_stages
        self.reduce = nn.Sequential(nn.Conv2d(feature_channels, reduce_channels, 1), nn.ReLU(inplace=True))
        layers: list[nn.Module] = []
        c = maps_channels + reduce_channels
        for co in channels:
            layers += [nn.ConvTranspose2d(c, co, kernel_size=4, stride=2, padding=1), nn.ReLU(inplace=True)]
            c = co
        self.up = nn.Sequential(*layers)
        self.out = nn.Conv2d(c, maps_channels, 1)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, outputs: list[tuple[torch.Tensor, torch.Tensor]],
                features: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
        reduced = self.reduce(features)
        nb = NUM_BELIEF * self.num_objects
        result = []
        for i, (belief, affinity) in enumerate(outputs):
            maps = torch.cat([belief, affinity], 1)
            up = F.interpolate(maps, scale_factor=8, mode="bilinear", align_corners=False)
            if self.decode_stages == "all" or i == len(outputs) - 1:
                up = up + self.out(self.up(torch.cat([maps, reduced], 1)))
            result.append((up[:, :nb], up[:, nb:]))
        return result


def _init_weights(module: nn.Module) -> None:
    """Kaiming (fan_out, ReLU) for convs, as torchvision's VGG; BN to identity."""
    for m in module.modules():
        if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)):
            nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, (nn.BatchNorm2d, nn.GroupNorm)):
            nn.init.ones_(m.weight)
            nn.init.zeros_(m.bias)


# ----------------------------------------------------------------------------- the network
class DopeNetwork(nn.Module):
    """DOPE belief/affinity network (``arch: dope``) or its small sibling (``arch: lite``).

    Args:
        arch: "dope" (official layout) or "lite" (:mod:`dope_hope.model.lite`).
        head: 50 (maps at stride 8) or 400 (full resolution, dope only; lite also takes 100,
            stride 4).
        stages: number of refinement stages (dope: 1..6, official 6).
        decoder: options of :class:`UpsamplingDecoder` for head 400.
        lite: options of :class:`dope_hope.model.lite.LiteTrunk` for arch lite.
        num_objects: N, the objects the network detects (a belief/affinity group each).

    Attributes:
        stride: image pixels per map cell (8, 4 or 1).
        num_stages: number of (belief, affinity) pairs ``forward`` returns.
    """

    def __init__(self, arch: str = "dope", head: int = 50, stages: int = 6,
                 decoder: dict[str, Any] | None = None, lite: dict[str, Any] | None = None,
                 num_objects: int = 1):
        super().__init__()
        self.arch = arch
        self.head = int(head)
        self.num_stages = int(stages)
        if isinstance(num_objects, bool) or not isinstance(num_objects, int) or num_objects < 1:
            raise ConfigError(f"model.num_objects must be a whole number >= 1, got {num_objects!r}")
        self.num_objects = n = num_objects
        if arch == "dope":
            if self.head not in HEAD_STRIDES:
                raise ConfigError(f"model.head must be 50 or 400 for arch dope, got {head!r}")
            if not 1 <= self.num_stages <= 6:
                raise ConfigError(f"model.stages must be 1..6 for arch dope, got {stages!r}")
            self.vgg = vgg_trunk()
            for s in range(1, self.num_stages + 1):
                in_ch = FEATURE_CHANNELS if s == 1 else FEATURE_CHANNELS + NUM_MAPS * n
                # Registration order as in the official code does not matter for loading.
                setattr(self, f"m{s}_2", dope_stage(in_ch, NUM_BELIEF * n, first=s == 1))
                setattr(self, f"m{s}_1", dope_stage(in_ch, NUM_AFFINITY * n, first=s == 1))
            _init_weights(self)
            self.stride = HEAD_STRIDES[self.head]
            if self.head == 400:
                opts = dict(decoder or {})
                self.decoder = UpsamplingDecoder(
                    FEATURE_CHANNELS, int(opts.pop("reduce_channels", 32)),
                    tuple(opts.pop("channels", (32, 16, 16))), str(opts.pop("stages", "all")), n)
                if opts:
                    raise ConfigError(f"unknown model.decoder options: {', '.join(sorted(opts))}")
        elif arch == "lite":
            known = set(inspect.signature(LiteTrunk).parameters) - {"head", "stages", "num_objects"}
            unknown = sorted(set(lite or {}) - known)
            if unknown:
                raise ConfigError(f"unknown model.lite options: {', '.join(unknown)} (known: {', '.join(sorted(known))})")
            self.lite = LiteTrunk(head=self.head, stages=self.num_stages, num_objects=n, **(lite or {}))
            self.stride = self.lite.stride
            _init_weights(self)
            self.lite.reset_output_layers()
        else:
            raise ConfigError(f"model.arch must be 'dope' or 'lite', got {arch!r}")

    def texture_features(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) normalized RGB -> (B, C, H/4, W/4): the trunk's first layers (lite: its
        stem and first downsampling, C = 2 x width; dope: VGG19's first two blocks, C = 128),
        local texture and edges before any keypoint is decided (the appearance check compares
        renders with the image by them: :mod:`dope_hope.inference.appearance`)."""
        if self.arch == "lite":
            return self.lite.texture_features(x)
        return self.vgg[:VGG_STRIDE4_LAYERS](x)

    def forward(self, x: torch.Tensor) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """(B, 3, H, W) normalized RGB -> [(belief (B, 9N, h, w), affinity (B, 16N, h, w))] per stage."""
        if self.arch == "lite":
            return self.lite(x)
        features = self.vgg(x)
        outputs: list[tuple[torch.Tensor, torch.Tensor]] = []
        inp = features
        for s in range(1, self.num_stages + 1):
            belief = getattr(self, f"m{s}_2")(inp)
            affinity = getattr(self, f"m{s}_1")(inp)
            outputs.append((belief, affinity))
            if s < self.num_stages:
                inp = torch.cat([belief, affinity, features], 1)
        if self.head == 400:
            outputs = self.decoder(outputs, features)
        return outputs


def model_section(config: dict[str, Any]) -> dict[str, Any]:
    """The ``model`` section of a full config (or the dict itself if it is already one; a
    config that leaves the section out: {}, every key its default)."""
    if "model" in config and isinstance(config["model"], dict):
        return config["model"]
    if "model" in config or set(config) & {"input", "targets", "train", "augment"}:
        return {}
    return config


def build_model(config: dict[str, Any] | str, load_backbone: bool = True) -> DopeNetwork:
    """Build a DopeNetwork from a config name (``"lite"``, ``"dope_dr_50"``, ``"dope_dr_400"``:
    the packaged YAML files), a full config or its ``model`` section.

    Keys: those of :class:`~dope_hope.model.settings.ModelSettings` (their defaults where
    the section leaves them out); unknown keys raise ConfigError. ``backbone_weights``: a
    LOCAL torchvision VGG19 state-dict file loaded into the trunk when ``load_backbone``
    (nothing is ever downloaded; checkpoint loading passes False, its weights win).
    """
    if isinstance(config, str):
        config = load_config(config)
    m = ModelSettings.from_mapping(model_section(config))
    backbone = m.backbone_weights
    model = DopeNetwork(arch=m.arch, head=m.head, stages=m.stages, decoder=m.decoder.to_dict(),
                        lite=m.lite.to_dict(), num_objects=m.num_objects)
    if backbone and load_backbone:
        load_backbone_weights(model, backbone)
    return model


def load_backbone_weights(model: DopeNetwork, path: str | os.PathLike) -> list[str]:
    """Copy ImageNet VGG19 conv weights from a local torchvision file into ``model.vgg``.

    Accepts a state dict of ``torchvision.models.vgg19`` (keys ``features.<i>.weight|bias``;
    classifier keys are ignored). Returns the ``vgg.*`` keys loaded, in model order (20
    tensors: conv1_1 .. conv4_2). Raises ModelFileError naming the file for anything else.
    """
    if getattr(model, "arch", None) != "dope":
        raise ConfigError("backbone_weights applies to arch dope only (the VGG19 trunk)")

    try:
        require_file(path, "backbone weights file")
    except DopeHopeError as exc:
        raise ModelFileError(path, exc.problem) from None
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure is a bad file
        raise ModelFileError(path, f"not a readable torch weights file ({type(exc).__name__})") from None
    if not isinstance(state, dict):
        raise ModelFileError(path, "expected a VGG19 state dict")
    if "state_dict" in state and isinstance(state["state_dict"], dict):
        state = state["state_dict"]
    own = model.vgg.state_dict()
    mapped: dict[str, torch.Tensor] = {}
    for key, value in state.items():
        key = key.removeprefix("module.")
        if not key.startswith("features."):
            continue
        idx, _, name = key[len("features."):].partition(".")
        if idx.isdigit() and int(idx) < VGG_LAYERS_KEPT:
            target = f"{idx}.{name}"
            if target not in own or own[target].shape != value.shape:
                raise ModelFileError(path, f"{key} {tuple(value.shape)} does not fit the VGG19 trunk")
            mapped[target] = value
    expected = {k for k in own if int(k.split(".")[0]) < VGG_LAYERS_KEPT}
    missing = sorted(expected - set(mapped))
    if missing:
        raise ModelFileError(path, f"not VGG19 weights: missing features.{missing[0]} "
                                   f"(and {len(missing) - 1} more)")
    model.vgg.load_state_dict(mapped, strict=False)
    return [f"vgg.{k}" for k in own if k in mapped]


# ----------------------------------------------------------------------------- many objects
def num_objects_of(config: dict[str, Any]) -> int:
    """``model.num_objects`` of a full config or model section (1 when absent)."""
    return ModelSettings.from_mapping(model_section(config)).num_objects


def _widen_rows(t: torch.Tensor, per: tuple[int, ...], n: int) -> torch.Tensor:
    """Output channels (dim 0) laid out as consecutive blocks of sizes ``per`` (e.g. 9 belief
    then 16 affinity), each block repeated ``n`` times in place: [b, b, ..., a, a, ...]."""
    blocks = torch.split(t, list(per), dim=0)
    return torch.cat([b.repeat((n,) + (1,) * (t.ndim - 1)) for b in blocks], 0)


def _widen_map_inputs(t: torch.Tensor, per: tuple[int, ...], n: int, dim: int) -> torch.Tensor:
    """Input channels along ``dim`` whose first sum(per) channels read maps (blocks ``per``,
    the rest features): each map block repeated ``n`` times and divided by ``n`` (so N
    identical groups sum to the one group's input), the feature channels unchanged."""
    k = sum(per)
    maps, rest = t.narrow(dim, 0, k), t.narrow(dim, k, t.shape[dim] - k)
    blocks = torch.split(maps, list(per), dim=dim)
    reps = [1] * t.ndim
    reps[dim] = n
    return torch.cat([b.repeat(reps) / n for b in blocks] + [rest], dim)


def widen_to_objects(state: dict[str, torch.Tensor], config: dict[str, Any],
                     num_objects: int) -> dict[str, torch.Tensor]:
    """A one-object state dict of ``config``'s architecture -> the state dict of the same
    architecture with ``num_objects`` belief/affinity groups.

    Every group starts as a copy of the one group: the output convs' rows are repeated per
    object, and the convs that read the previous stage's maps (stages s > 1; the lite stages;
    the 400-px decoder) take their map-input weights repeated and divided by N, so that with
    N identical groups each group's output equals the one-object network's (stage 1's groups
    are identical, hence every later stage's). ``config`` describes the architecture
    (its ``num_objects`` is ignored); ConfigError when ``state`` does not fit one object of it.
    """
    n = int(num_objects)
    if n < 1:
        raise ConfigError(f"num_objects must be >= 1, got {num_objects!r}")
    section = {k: v for k, v in model_section(config).items() if k != "num_objects"}
    with torch.device("meta"):
        one = build_model({**section, "num_objects": 1}, load_backbone=False)
    expected = one.state_dict()
    bad = sorted(set(expected) ^ set(state)) or \
        [k for k in expected if tuple(state[k].shape) != tuple(expected[k].shape)]
    if bad:
        raise ConfigError(f"widen_to_objects: the state dict is not a one-object {section.get('arch', 'dope')} "
                          f"network of this config (first mismatch: {bad[0]})")
    if n == 1:
        return dict(state)
    out = dict(state)
    for key, value in state.items():
        rule = _widen_rule(one, key)
        if rule is None:
            continue
        rows, inputs, in_dim = rule
        v = value
        if inputs is not None and v.ndim > in_dim:
            v = _widen_map_inputs(v, inputs, n, in_dim)
        if rows is not None:
            v = _widen_rows(v, rows, n)
        out[key] = v.contiguous()
    return out


def _widen_rule(one: DopeNetwork, key: str) -> tuple[tuple[int, ...] | None, tuple[int, ...] | None, int] | None:
    """How :func:`widen_to_objects` treats one parameter: (output blocks to repeat or None,
    map-input blocks to repeat / N or None, the input dim of the weight) or None (shared)."""
    parts = key.split(".")
    maps = (NUM_BELIEF, NUM_AFFINITY)
    if one.arch == "lite":
        if parts[:2] != ["lite", "stages"]:
            return None
        stage, layer = int(parts[2]), int(parts[3])
        last = len(one.lite.stages[stage]) - 1
        if layer == last:
            return maps, None, 1
        if stage > 0 and layer == 0 and parts[4] == "0" and parts[-1] == "weight":
            return None, maps, 1  # the first conv_bn_relu's conv: weight (C, 25 + F, 3, 3)
        return None
    if parts[0] == "decoder":
        if parts[1] == "out":
            return maps, None, 1
        if parts[1] == "up" and parts[2] == "0" and parts[-1] == "weight":
            return None, maps, 0  # ConvTranspose2d weight: (in, out, k, k)
        return None
    name = parts[0]
    if len(name) > 1 and name[0] == "m" and "_" in name:
        stage, branch = name[1:].split("_")
        branch_out = (NUM_BELIEF,) if branch == "2" else (NUM_AFFINITY,)
        seq = getattr(one, name)
        layer = int(parts[1])
        if layer == len(seq) - 1:
            return branch_out, None, 1
        if int(stage) > 1 and layer == 0 and parts[-1] == "weight":
            return None, maps, 1
    return None
