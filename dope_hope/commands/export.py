"""Export a checkpoint to ONNX: native or Isaac ROS layout, fp32 or static INT8.

Examples:
  dope-hope export --weights runs/ketchup/best.pt --out ketchup.onnx
  dope-hope export --weights best.pt --out ketchup.onnx --dynamic
  dope-hope export --weights best.pt --out ketchup_isaac.onnx --layout isaac-ros
  dope-hope export --weights best.pt --out ketchup_int8.onnx --int8 --calibration synth/val

The .onnx file is self-contained: `dope-hope infer IMAGE --weights ketchup.onnx` needs no
checkpoint (object class, cuboid size, keypoint order, normalization and map stride are in
its metadata). native: input `image` (N,3,H,W) ImageNet-normalized, outputs `belief` and
`affinity` of the last stage. isaac-ros: input `input` (1,3,480,640 by default) normalized
like the Isaac ROS image encoder (mean = std = 0.5, or --isaac-normalization imagenet),
output `output` (1,25,H/8,W/8) = 9 belief + 16 affinity channels, for Isaac ROS DOPE.
--int8 writes a statically quantized model (QDQ, per-channel) calibrated on --calibration
images and prints its deviation from fp32.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("--weights", type=Path, required=True, metavar="CKPT", help="dope-hope checkpoint")
    parser.add_argument("--out", type=Path, required=True, metavar="FILE.onnx", help="ONNX file to write")
    parser.add_argument("--height", type=int, help="input height, px, multiple of 8 (default: training "
                                                   "size; isaac-ros: 480)")
    parser.add_argument("--width", type=int, help="input width, px, multiple of 8 (default: training "
                                                  "size; isaac-ros: 640)")
    parser.add_argument("--dynamic", action="store_true", help="dynamic input height and width (native only)")
    parser.add_argument("--layout", choices=("native", "isaac-ros"), default="native",
                        help="graph layout (default native)")
    parser.add_argument("--isaac-normalization", choices=("half", "imagenet"), default="half",
                        help="isaac-ros: the Isaac ROS image encoder's mean/std (half = 0.5/0.5, the "
                             "isaac_ros_dope_tensor_rt.launch.py default; imagenet = the newer "
                             "isaac_ros_dope_core.launch.py default)")
    parser.add_argument("--int8", action="store_true", help="static INT8 quantization (needs --calibration)")
    parser.add_argument("--calibration", type=Path, metavar="DIR", help="folder of calibration images")
    parser.add_argument("--calibration-images", type=int, default=32, metavar="N",
                        help="calibration images used (default 32)")
    parser.add_argument("--calibration-method", choices=("minmax", "entropy", "percentile"),
                        default="minmax", help="activation range calibration (default minmax; entropy "
                                               "and percentile hold whole activations of every "
                                               "calibration image in memory: few images for DR-50)")
    parser.add_argument("--opset", type=int, default=17, help="ONNX opset, 11..20 (default 17)")
    parser.add_argument("--json", action="store_true", help="print the result as one JSON object")


def run(args: argparse.Namespace) -> int:
    from dope_hope.export.pipeline import export_checkpoint

    res = export_checkpoint(args.weights, args.out, height=args.height, width=args.width,
                            dynamic=args.dynamic, layout=args.layout, int8=args.int8,
                            calibration=args.calibration, opset=args.opset,
                            isaac_encoder=args.isaac_normalization,
                            calibration_images=args.calibration_images,
                            calibration_method=args.calibration_method)
    info = res.info
    size = "dynamic" if info.fixed_input_hw is None else f"{info.fixed_input_hw[0]}x{info.fixed_input_hw[1]}"
    if args.json:
        record = {"path": str(res.path), "size_bytes": res.size_bytes, "seconds": round(res.seconds, 2),
                  "layout": info.layout, "precision": info.precision, "opset": info.opset, "input": size,
                  "verify_max_abs": res.verify_max_abs, "metadata": info.to_metadata()}
        if res.int8 is not None:
            record["int8_deviation"] = vars(res.int8)
        print(json.dumps(record))
        return 0
    print(f"wrote {res.path} ({res.size_bytes / 1e6:.1f} MB, {res.seconds:.1f} s): {info.class_name}, "
          f"{info.arch} head {info.head} (stride {info.stride}), {info.layout} layout, {info.precision}, "
          f"opset {info.opset}, input {size}")
    print(f"  fp32 graph vs PyTorch on a random input: max |d| = {res.verify_max_abs:.2e}")
    if res.int8 is not None:
        print(f"  INT8 vs fp32: {res.int8.summary()}")
    if info.layout == "isaac-ros":
        dims = json.loads(info.extra["isaac_ros.object_dimensions_cm"])
        print(f"  Isaac ROS: network_image_height:={info.fixed_input_hw[0]} network_image_width:="
              f"{info.fixed_input_hw[1]} encoder_image_mean:='{list(info.input_mean)}' "
              f"encoder_image_stddev:='{list(info.input_std)}'; dope_config.yaml dimensions "
              f"\"{info.class_name}\": {dims} (cm, {info.frame} frame)")
    return 0
