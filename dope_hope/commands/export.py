"""Export a checkpoint to ONNX: native or Isaac ROS layout, fp32 or static INT8.

Examples:
  dope-hope export --weights runs/ketchup/best.pt --out ketchup.onnx
  dope-hope export --weights best.pt --out ketchup.onnx --dynamic
  dope-hope export --weights best.pt --out ketchup_isaac.onnx --layout isaac-ros
  dope-hope export --weights best.pt --out ketchup_isaac.onnx --layout isaac-ros --isaac-ros-version 3.1
  dope-hope export --weights best.pt --out ketchup_int8.onnx --int8 --calibration synth/val
  dope-hope export --weights shelf.pt --out ketchup_isaac.onnx --layout isaac-ros --object Ketchup

The .onnx file is self-contained: `dope-hope infer IMAGE --weights ketchup.onnx` needs no
checkpoint (object class, cuboid size, keypoint order, normalization and map stride are in
its metadata). native: input `image` (N,3,H,W) ImageNet-normalized, outputs `belief` and
`affinity` of the last stage. isaac-ros: input `input` (1,3,480,640 by default) normalized
like the Isaac ROS image encoder, output `output` (1,25,H/8,W/8) = 9 belief + 16 affinity
channels in the vertex order of --isaac-ros-version's DOPE decoder (3.2 turned it 180 deg
about z), so that Isaac ROS publishes the mesh-frame pose; stride-4 maps (lite head 100) are
average-pooled to stride 8 in the graph. The command prints every launch argument and the
dope_config.yaml `dimensions` entry (cm, mesh frame) to use.
--int8 writes a statically quantized model (QDQ, per-channel) calibrated on --calibration
images and prints its deviation from fp32.
A multi-object model exports to one file holding every object (native), or with --object
NAME to a file of that object's channels only; Isaac ROS DOPE runs one object per model, so
--layout isaac-ros of a multi-object model needs --object.
"""
from __future__ import annotations

import argparse
import json
import shlex
from dataclasses import replace
from pathlib import Path

from dope_hope.commands.argtypes import positive_int, working_side
from dope_hope.commands.settings import add_settings_arguments, command_settings
from dope_hope.errors import ConfigError
from dope_hope.export.isaac_ros import (
    ISAAC_ROS_CURRENT,
    dope_config_entry,
    isaac_ros_release,
    launch_arguments,
)

# The library is imported inside the functions: cli.py imports every command to build --help,
# which must not pay for numpy, OpenCV or torch.


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--weights", type=Path, required=True, metavar="CKPT", help="dope-hope checkpoint")
    parser.add_argument("--out", type=Path, required=True, metavar="FILE.onnx", help="ONNX file to write")
    parser.add_argument("--height", type=working_side, help="input height, px, multiple of 8 (default: "
                                                            "training size; isaac-ros: 480)")
    parser.add_argument("--width", type=working_side, help="input width, px, multiple of 8 (default: "
                                                           "training size; isaac-ros: 640)")
    parser.add_argument("--dynamic", action="store_true", help="dynamic input height and width (native only)")
    parser.add_argument("--layout", choices=("native", "isaac-ros"),
                        help="graph layout (default native)")
    parser.add_argument("--isaac-ros-version", metavar="X.Y",
                        help=f"isaac-ros: the Isaac ROS release to deploy on (default and newest known "
                             f"{ISAAC_ROS_CURRENT}); 3.2 and later order the cuboid vertices differently "
                             "from 3.1 and earlier")
    parser.add_argument("--isaac-normalization", choices=("half", "imagenet"),
                        help="isaac-ros: the image encoder's mean/std (half = 0.5/0.5, imagenet) "
                             "(default: the release's launch default: half up to 3.1, imagenet since 3.2)")
    parser.add_argument("--object", metavar="NAME",
                        help="export this object's channels only (a multi-object model; needed for "
                             "--layout isaac-ros, which holds one object)")
    parser.add_argument("--int8", action="store_true", help="static INT8 quantization (needs --calibration)")
    parser.add_argument("--calibration", type=Path, metavar="DIR", help="folder of calibration images")
    parser.add_argument("--calibration-images", type=positive_int, default=32, metavar="N",
                        help="calibration images used (default 32)")
    parser.add_argument("--calibration-method", choices=("minmax", "entropy", "percentile"),
                        default="minmax", help="activation range calibration (default minmax; entropy "
                                               "and percentile hold whole activations of every "
                                               "calibration image in memory: few images for DR-50)")
    parser.add_argument("--opset", type=int, help="ONNX opset, 11..20 (default 17)")
    add_settings_arguments(parser, "export")
    parser.add_argument("--json", action="store_true", help="print the result as one JSON object")


def run(args: argparse.Namespace) -> int:
    from dope_hope.export.pipeline import Int8Calibration, export_checkpoint
    from dope_hope.io.paths import output_file

    # the export section (--config, --set), then the flags that name its keys
    base = command_settings("export", args.config, args.overrides).export
    flags = {"layout": args.layout, "dynamic": True if args.dynamic else None, "opset": args.opset,
             "isaac_encoder": args.isaac_normalization, "isaac_ros_version": args.isaac_ros_version,
             "object_name": args.object,
             "input_hw": None if args.height is None or args.width is None else (args.height, args.width)}
    settings = replace(base, **{k: v for k, v in flags.items() if v is not None})
    if settings.layout != "isaac-ros":
        for flag, value in (("--isaac-ros-version", args.isaac_ros_version),
                            ("--isaac-normalization", args.isaac_normalization)):
            if value is not None:
                raise ConfigError(f"{flag} applies only to --layout isaac-ros (this export: --layout {settings.layout})")
    if (args.height is None) != (args.width is None):
        raise ConfigError("give both --height and --width (or neither)")
    if args.int8 and args.calibration is None:
        raise ConfigError("--int8 needs --calibration DIR (a folder of representative images)")
    if args.calibration is not None and not args.int8:
        raise ConfigError("--calibration is only used with --int8")
    output_file(args.out)
    int8 = Int8Calibration(args.calibration, args.calibration_images, args.calibration_method) if args.int8 else None
    res = export_checkpoint(args.weights, args.out, settings, int8)
    info = res.info
    size = "dynamic" if info.fixed_input_hw is None else f"{info.fixed_input_hw[0]}x{info.fixed_input_hw[1]}"
    isaac = isaac_ros_deployment(info, res.path) if info.layout == "isaac-ros" else None
    if args.json:
        record = {"path": str(res.path), "size_bytes": res.size_bytes, "seconds": round(res.seconds, 2),
                  "layout": info.layout, "precision": info.precision, "opset": info.opset, "input": size,
                  "verify_max_abs": res.verify_max_abs, "metadata": info.to_metadata()}
        if res.int8 is not None:
            record["int8_deviation"] = vars(res.int8)
        if isaac is not None:
            record["isaac_ros"] = isaac
        print(json.dumps(record))
        return 0
    print(f"wrote {res.path} ({res.size_bytes / 1e6:.1f} MB, {res.seconds:.1f} s): {', '.join(info.class_names)}, "
          f"{info.arch} head {info.head} (stride {info.stride}), {info.layout} layout, {info.precision}, "
          f"opset {info.opset}, input {size}")
    print(f"  fp32 graph vs PyTorch on a random input: max |d| = {res.verify_max_abs:.2e}")
    if res.int8 is not None:
        print(f"  INT8 vs fp32: {res.int8.summary()}")
        from dope_hope.export.int8 import cpu_int8_support

        gains, isa = cpu_int8_support()
        if gains is False:
            print(f"  note: this machine's CPU ({isa}) runs onnxruntime INT8 convolutions at about "
                  "fp32 speed; the INT8 file pays off on CPUs with VNNI (x86) or dot-product (ARM) "
                  "instructions, else use the fp32 export")
    if isaac is not None:
        resampled = info.extra.get("isaac_ros.resampled_from_stride")
        print(f"  Isaac ROS {isaac['version']}: {isaac['launch_file']} arguments (all of them; "
              f"* = not the default):")
        for name, value in isaac["launch_arguments"].items():
            mark = "*" if name in isaac["changed"] else " "
            print(f"   {mark} {name}:={_shell_word(value)}")
        if "input_image_width" in isaac["launch_arguments"]:
            print("    (input_image_width/height: your camera's image size)")
        print(f"  dope_config.yaml (dope: ros__parameters: dimensions:, cm, mesh-frame x, y, z): "
              f"{isaac['dope_config_entry']}")
        if _is_hope_object(info.class_name):
            print("    (replaces the stock entry, which lists the legacy frame of NVIDIA's HOPE weights)")
        print(f"  Isaac ROS then publishes the mesh-frame pose (output channels in its vertex order "
              f"{isaac['channel_order']}" + (f"; stride-{resampled} maps average-pooled to stride 8"
                                             if resampled else "") + ")")
    return 0


def isaac_ros_deployment(info, path: Path) -> dict:
    """What Isaac ROS needs for an isaac-ros file: launch arguments, config entry, channel order."""
    release = isaac_ros_release(info.extra["isaac_ros.version"])
    args = launch_arguments(release, path, info.fixed_input_hw, info.extra["isaac_ros.encoder"], info.class_name)
    return {"version": release.version, "launch_file": release.launch_file, "launch_arguments": args,
            "changed": [k for k, v in args.items() if v != release.launch_defaults[k]],
            "dope_config_entry": dope_config_entry(info.class_name, info.size_m),
            "channel_order": json.loads(info.extra["isaac_ros.channel_order"])}


def _is_hope_object(name: str) -> bool:
    from dope_hope.catalog import HOPE_OBJECTS

    return name.lower() in {o.name.lower() for o in HOPE_OBJECTS}


def _shell_word(value: str) -> str:
    """A launch argument value as one shell word ('...' when it holds spaces or brackets)."""
    return shlex.quote(value) if value else "''"
