"""Print a command's effective settings: its defaults, with a --config file and --set items on
top, as the command would use them (YAML, every key; one line and exit status 2 for an
unknown key or a bad value, naming section.key, as the command itself would say).

Examples:
  dope-hope settings train --config lite --set train.lr=1e-3
  dope-hope settings infer --set tracking.reprojection_px=2.0
  dope-hope settings synth --config demo > my_synth.yaml

Commands with settings: synth (the generator's ranges, dope_hope/configs/synth.yaml), train
(a training recipe: model, input, targets, train, augment; default config lite), infer, demo and
bop-submit (the inference options: top-level keys and one section per stage,
dope_hope/configs/infer.yaml), export (the export section), adapt (labels, carry, finetune and
the labelling's inference options, infer). Each of them takes the same
--config FILE and --set SECTION.KEY=VALUE; a --config file holds only what it changes. For
infer, a model whose file records its own threshold uses it as min_score unless --config or
--set gives one.
"""
from __future__ import annotations

import argparse
import importlib
from typing import Any

from dope_hope.config import load_settings, merge, settings_from_layers, settings_layers, settings_yaml

#: The commands that have settings: command -> (module, settings class, default --config).
SETTINGS_OF: dict[str, tuple[str, str, str | None]] = {
    "synth": ("dope_hope.synth.settings", "SynthSettings", "synth"),
    "train": ("dope_hope.training.settings", "TrainConfig", "lite"),
    "infer": ("dope_hope.inference.options", "InferenceOptions", None),
    "demo": ("dope_hope.inference.options", "InferenceOptions", None),
    "bop-submit": ("dope_hope.inference.options", "InferenceOptions", None),
    "export": ("dope_hope.export.to_onnx", "ExportConfig", None),
    "adapt": ("dope_hope.adaptation.settings", "AdaptConfig", None),
}


def add_settings_arguments(parser: argparse.ArgumentParser, command: str, config_help: str | None = None) -> None:
    """The --config and --set options of ``command`` (see :data:`SETTINGS_OF`)."""
    default = SETTINGS_OF[command][2]
    parser.add_argument("--config", default=default, metavar="NAME|FILE",
                        help=config_help or ("settings file (YAML, only the keys it changes) or a packaged "
                                             f"config's name; `dope-hope settings {command}` prints them all"))
    parser.add_argument("--set", nargs="+", action="extend", default=[], dest="overrides",
                        metavar="SECTION.KEY=VALUE",
                        help="settings on top of --config, values as YAML, e.g. "
                             + {"synth": "--set target.count=[1,1] lights.shadows=true",
                                "train": "--set train.lr=1e-3 augment.rotation_deg=30",
                                "export": "--set export.opset=18",
                                "adapt": "--set finetune.rounds=3 labels.min_support=0.7"}.get(command, "--set tracking.reprojection_px=2.0 "
                                                                                 "decode.threshold=0.2"))


def add_preset_arguments(parser: argparse.ArgumentParser, default_text: str) -> None:
    """``--fast`` / ``--accurate``: the inference preset (dope_hope.inference.options.PRESETS) the
    --config and --set options apply over; ``default_text`` says which one runs without either."""
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--fast", dest="preset", action="store_const", const="fast",
                       help="one working size, no turns, ICP only with --icp: the frame rate first "
                            f"(the packaged defaults; {default_text})")
    group.add_argument("--accurate", dest="preset", action="store_const", const="accurate",
                       help="three working sizes, ICP where there is depth and a mesh or box, the trained "
                            f"turns where not (dope_hope/configs/infer_accurate.yaml; {default_text})")


def settings_class(command: str) -> Any:
    """The settings class of ``command``."""
    module, name, _ = SETTINGS_OF[command]
    return getattr(importlib.import_module(module), name)


def command_settings(command: str, config: Any, overrides: list[str]) -> Any:
    """``command``'s effective settings (:func:`dope_hope.config.load_settings`)."""
    return load_settings(settings_class(command), config, overrides)


def given_settings(command: str, config: Any, overrides: list[str]) -> dict[str, Any]:
    """What ``config`` and ``overrides`` set, nested as a file writes it (checked first: one
    line naming the file or --set item and section.key for a bad one); each read once
    (:func:`dope_hope.config.settings_layers`). The command's own default config is checked
    and left out: it is no setting a user gave."""
    layers = settings_layers(config, overrides)
    settings_from_layers(settings_class(command), layers)
    given: dict[str, Any] = {}
    default_first = config is not None and config == SETTINGS_OF[command][2]
    for _, layer in layers[1 if default_first else 0:]:
        given = merge(given, dict(layer))
    return given


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("command_name", choices=sorted(SETTINGS_OF), metavar="COMMAND",
                        help=f"the command: {', '.join(sorted(SETTINGS_OF))}")
    parser.add_argument("--config", metavar="NAME|FILE",
                        help="the command's --config (default: the command's own default)")
    parser.add_argument("--set", nargs="+", action="extend", default=[], dest="overrides",
                        metavar="SECTION.KEY=VALUE", help="the command's --set items")


def run(args: argparse.Namespace) -> int:
    config = args.config if args.config is not None else SETTINGS_OF[args.command_name][2]
    print(settings_yaml(command_settings(args.command_name, config, args.overrides)), end="")
    return 0
