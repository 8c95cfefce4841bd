"""Teach a model the lab's own domain from its unlabelled recordings, with depth as the teacher.

The model (--weights) labels the frames itself: each pose it finds with -LS + ICP at three
working sizes is kept only where the depth confirms it (the share of its visible surface the
depth measures where the pose puts it, the residual, its silhouette on the depth edges, its
score), and a confirmed pose is carried by the tracker into the neighbouring frames where the
model missed the object, re-fitted there by ICP and kept where the depth confirms it too. The
model is then fine-tuned on those labels mixed with the synthetic frames it was trained on,
and labels again with what it learned (rounds). Every step resumes: run the same command again.

    dope-hope adapt lab.mcap --weights runs/ketchup/best.pt --mesh Ketchup/textured.obj --out adapt/ketchup
    dope-hope adapt frames/ --weights best.pt --mesh Ketchup/textured.obj --synthetic data/ketchup \\
        --set finetune.rounds=3 finetune.time_budget_min=20 --preview --out adapt/ketchup

Inputs: a recording (ROS 1 bag, ROS 2 bag / MCAP: its colour, registered depth and camera_info
topics, as for infer), a video with its camera (--camera) and its depth images (--depth DIR:
frame i is the folder's i-th file), or images / folders / globs of RGB-D frames (each with its
registered depth and camera, as `infer --depth auto` finds them; --camera for all).
Outputs in --out: frames/ (the frames read), round_N/labels/ (the labelled frames, DOPE format,
each label's evidence under "adapt"; labels.jsonl with the rejected poses and why),
round_N/train/ (the round's training run), preview_round_N.png (--preview: kept and rejected
labels), adapted.pt (the adapted model; its checkpoint records what it adapted on).
Settings (`dope-hope settings adapt`): labels.* (when the depth confirms a pose), carry.*,
finetune.* (rounds, time_budget_min, synthetic_ratio, lr, steps), infer.* (the labelling's
inference options).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from dope_hope.commands.argtypes import parse_mesh_units, positive_float, positive_int
from dope_hope.commands.settings import add_settings_arguments

# The library is imported inside the functions: cli.py imports every command to build --help.


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("inputs", nargs="+", metavar="INPUT",
                        help="a recording (.bag, .mcap, ROS 2 bag folder), a video, or RGB-D images / folders")
    parser.add_argument("--weights", required=True, type=Path, metavar="FILE", help="the model to adapt (.pt)")
    parser.add_argument("--mesh", required=True, type=Path, metavar="FILE", help="the object's mesh")
    parser.add_argument("--mesh-units", action="append", default=[], metavar="UNIT",
                        help="unit of the mesh file, m, cm or mm (default: .obj cm, .ply mm)")
    parser.add_argument("--out", required=True, type=Path, metavar="DIR", help="the job's folder")
    parser.add_argument("--synthetic", action="append", type=Path, metavar="DIR",
                        help="synthetic frames to mix into the training (default: the training folders the "
                             "checkpoint records, where they exist); repeat for several")
    parser.add_argument("--time-budget", type=positive_float, metavar="MIN",
                        help="minutes of training, all rounds together (finetune.time_budget_min)")
    parser.add_argument("--max-frames", type=positive_int, metavar="N", help="read at most N frames")
    parser.add_argument("--preview", action="store_true",
                        help="write preview_round_N.png: kept and rejected labels with their evidence")
    src = parser.add_argument_group("frames")
    src.add_argument("--camera", type=Path, metavar="FILE",
                     help="intrinsics of every frame: K.json or a ROS camera_info YAML (a video needs it)")
    src.add_argument("--depth", type=Path, metavar="DIR", help="a video's depth images, one per frame")
    src.add_argument("--depth-scale", type=positive_float, metavar="MM_PER_UNIT",
                     help="millimetres per depth unit (default: the annotation's, else 1)")
    src.add_argument("--image-topic", metavar="TOPIC", help="a recording's colour topic")
    src.add_argument("--depth-topic", metavar="TOPIC", help="a recording's registered depth topic")
    src.add_argument("--camera-info-topic", metavar="TOPIC", help="a recording's camera_info topic")
    add_settings_arguments(parser, "adapt")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _adapt_note(message: str) -> None:
    print(f"dope-hope adapt: {message}", file=sys.stderr, flush=True)


def run(args: argparse.Namespace) -> int:
    from dope_hope.commands.settings import command_settings

    settings = command_settings("adapt", args.config, list(args.overrides))
    if args.time_budget is not None:
        from dataclasses import replace

        settings = replace(settings, finetune=replace(settings.finetune, time_budget_min=args.time_budget))
    units = parse_mesh_units(args.mesh_units)
    if isinstance(units, dict):
        from dope_hope.errors import ConfigError

        raise ConfigError("--mesh-units: one unit for the one mesh (m, cm or mm), not NAME=UNIT")
    camera = None
    if args.camera is not None:
        from dope_hope.io.camera import read_camera_file

        camera = read_camera_file(args.camera)
    from dope_hope.adaptation.run import adapt

    result = adapt(args.inputs, args.weights, args.mesh, args.out, mesh_units=units, synthetic=args.synthetic,
                   settings=settings, camera=camera, depth=args.depth, depth_scale_mm=args.depth_scale,
                   image_topic=args.image_topic, depth_topic=args.depth_topic,
                   camera_info_topic=args.camera_info_topic, max_frames=args.max_frames, preview=args.preview,
                   progress=not args.no_progress, note=_adapt_note)
    if result.weights is None:
        _adapt_note(f"training {result.status}: run the same command again to resume")
        return {"interrupted": 130, "terminated": 143}.get(result.status, 1)
    print(f"adapted model: {result.weights}")
    return 0
