"""Detect objects and estimate their 6-DoF poses in images, videos and camera streams.

Examples:
  dope-hope infer frame.png --weights ketchup.pt --camera K.json
  dope-hope infer scene/ --weights ketchup.pt --weights mustard.onnx --depth auto --out res/
  dope-hope infer 'hope/val/**/*_rgb.jpg' --weights ketchup.pt --depth auto --mesh meshes/
  dope-hope infer clip.mp4 --camera camera_info.yaml --out res/clip
  dope-hope infer 0 --camera camera_info.yaml --show            (camera 0; Ctrl-C or q stops)
  dope-hope infer realsense --icp --mesh meshes/                (pip install "dope-hope[realsense]")
  dope-hope infer robot.bag --track --foxglove --out res/robot  (pip install "dope-hope[ros]")
  dope-hope infer scene/ --weights shelf.pt --classes Ketchup Mustard --camera K.json
  dope-hope infer frame.png --mesh my_object.obj --camera K.json   (a new object, no training)

Output: one JSON line per detection on stdout, in the predictions format that
`dope-hope evaluate` reads (image, class, score, R, t in metres, ls_applied, plus
quaternion_xyzw, keypoints_2d, bbox_2d = [u_min, v_min, u_max, v_max] pixels of the projected
object, time, ...); in --out: OUT/predictions.jsonl (all detections, written atomically at
the end), an overlay IMAGE.overlay.png per image (projected cuboids, axes, class and score)
and with --belief IMAGE.belief.CLASS.png (belief maps of each object).

A model of several objects (one belief/affinity group each) returns all of them from one
forward pass; --classes A B keeps a subset (objects of no model listed: exit 2; a model with
none of them is not run).

Inputs: image files, a folder (its images, not recursive; *.depth.png, *_depth.png, *.seg.png
and similar are skipped) or a quoted glob ('**' recurses). The "image" of each record is its
path relative to the folder / the glob's fixed prefix / the files' common folder (with inputs
from different folders: relative to their common folder, so names never repeat). With several
images, one that cannot be read is skipped with a warning and the run exits 2 at the end;
predictions.jsonl always lists what the overlays show.

Streams (one input): a video file (.mp4, .avi, .mov, .mkv, ...), a camera index (0, 1, ...;
a file named 0 is ./0) or realsense[:SERIAL] (an Intel RealSense: colour, depth aligned to
colour, intrinsics and depth scale from the device, -LS on every frame, --icp too). Records
add "frame" (index in the stream) and "timestamp_s" (seconds since the first frame: the
video's own timestamps, the camera's capture times); "image" is NAME#FRAME (clip.mp4#000012).
OUT/NAME.overlay.mp4 (mp4v; .avi MJPG where mp4v is missing) holds the overlays, one video
frame per source frame. A camera is read in a thread that keeps only the newest frame: frames
the loop cannot process in time are dropped and counted, never queued; a video file is
processed frame by frame unless --realtime plays it at its frame rate like a camera. The
end prints frames read / processed / dropped and the end-to-end frames/s. --show opens a live
window where a display exists. Ctrl-C (or q in the window) ends a stream; what was processed
is written.

Recordings (pip install "dope-hope[ros]"; no ROS installation needed): a ROS 1 .bag, a ROS 2
bag folder (sqlite3 or MCAP storage) or a ROS 2 .mcap / .db3 file is a stream too: its colour
image topic (Image rgb8/bgr8/mono8, CompressedImage jpeg/png), a registered depth topic (16UC1
mm, 32FC1 m, compressedDepth) paired by header stamp within --sync-tolerance, and the colour
CameraInfo (a distorted camera is undistorted, never taken as pinhole), chosen automatically
when unambiguous (RealSense names) or named with --image-topic / --depth-topic /
--camera-info-topic; --list-topics prints them and stops. Records add "stamp_ns" and
"frame_id" (the image header's); "image" is NAME#FRAME. OUT/NAME_poses/ is a ROS 2 bag (MCAP
storage; Foxglove opens NAME_poses.mcap, `ros2 bag play` the folder) holding per frame
vision_msgs/Detection3DArray, geometry_msgs/PoseArray, visualization_msgs/MarkerArray,
foxglove_msgs/ImageAnnotations, tf (camera -> CLASS_ID) and the overlay as a CompressedImage
(not with --no-overlay), on the image's stamp and frame_id (docs/formats/recordings.md).
--foxglove [PORT] (any stream) serves the same messages live to the Foxglove app
(ws://127.0.0.1:PORT); a file waits for the app to subscribe before it plays.

Tracking (--track, streams): each object gets a track_id (per class, stable while it stays
in view); R, t and quaternion_xyzw become the tracked pose (a constant-velocity filter on
SE(3) aware of the object's symmetries: smoother, no lag on steady motion), R_detected /
t_detected hold the frame's own estimate, and "tracked" says "detected" or, for a missed
object whose track is confirmed, "coasted" (its predicted pose, refined against the depth
where there is one; R_detected null) for a few frames. The overlay shows "#ID" per box.

Camera (never guessed): --camera K.json or a ROS camera_info YAML (camera_calibration's
ost.yaml or a CameraInfo message; non-zero distortion is removed from every frame, as
image_proc does), or --fx --fy --cx --cy, else each image's sibling annotation: DOPE
NNNNNN.json, HOPE NNNN.json for NNNN_rgb.jpg, or BOP scene_camera.json two levels up. K.json
may hold {"fx", "fy", "cx", "cy"}, {"K": 3x3}, {"cam_K": 9 numbers}, a DOPE camera_data block
or a HOPE camera block (optional width/height are checked against the image).

Depth (optional, enables the depth line search "-LS"): --depth PATH (one image only) or
--depth auto: each image's registered depth from its annotation's folder (DOPE
NNNNNN.depth.png, HOPE NNNN_depth.png, BOP ../depth/NNNNNN.png); images without one are
processed without -LS. --depth-scale gives millimetres per depth unit (BOP convention; default:
the annotation's, else 1 = uint16 millimetres); float depth images (EXR) are metres. --icp
(needs depth) then refines the whole pose, rotation included, by ICP against the depth
("-LS + ICP", dope_hope/refine/icp.py); each record says whether it was applied (icp_applied,
icp_reason).

Presets: images and folders run the "accurate" settings (three working sizes, ICP where there
is depth and a mesh or catalog box, the trained turns about a bottle's or can's axis where
not: dope_hope/configs/infer_accurate.yaml); video, cameras and recordings the packaged
defaults ("fast": one size, ICP only with --icp), to keep the frame rate. --fast / --accurate
choose the other; --config and --set apply on top.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from dope_hope.assets import DEMO_WEIGHTS  # used when --weights is not given
from dope_hope.commands.argtypes import (
    finite_float,
    fixed_device,
    parse_mesh_units,
    parse_up_axes,
    positive_float,
    positive_int,
    working_side,
)
from dope_hope.commands.settings import add_preset_arguments, add_settings_arguments, given_settings
from dope_hope.config import load_config
from dope_hope.errors import ConfigError, DopeHopeError
from dope_hope.ros.defaults import DEFAULT_FOXGLOVE_PORT, DEFAULT_SYNC_TOLERANCE_S  # plain numbers

# The library is imported inside the functions: cli.py imports every command to build --help,
# which must not pay for numpy, OpenCV or torch.

#: Frame rate of an overlay video when the source reports none.
FALLBACK_FPS = 30.0
#: Options of video and camera inputs only.
STREAM_OPTIONS = ("realtime", "max_frames", "show", "capture_size", "capture_fps", "track", "foxglove")
#: Options of recordings only.
RECORDING_OPTIONS = ("image_topic", "depth_topic", "camera_info_topic", "sync_tolerance", "list_topics")


def default_weights() -> Path | None:
    """The shipped demo model if this installation has it, else None."""
    return DEMO_WEIGHTS if DEMO_WEIGHTS.is_file() else None


def _default_min_score() -> float:
    """The inference options' min_score (dope_hope/configs/infer.yaml), read without the
    heavy imports of InferenceOptions."""
    return float(load_config("infer")["min_score"])


def _size(text: str) -> tuple[int, int]:
    w, sep, h = text.lower().partition("x")
    if not sep or not w.isdigit() or not h.isdigit() or int(w) < 1 or int(h) < 1:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT such as 640x480, got {text!r}")
    return int(w), int(h)


def _port(text: str) -> int:
    if not text.isdigit() or int(text) > 65535:
        raise argparse.ArgumentTypeError(f"expected a port number 0-65535 (0: any free port), got {text!r}")
    return int(text)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument("inputs", nargs="+", metavar="SOURCE",
                        help="image file(s), a folder of images, a quoted glob, a video file, a camera "
                             "index (0), realsense[:SERIAL] or a recording (.bag, .mcap, .db3, ROS 2 bag folder)")
    parser.add_argument("--weights", action="append", type=Path, metavar="W",
                        help="checkpoint (.pt/.pth) or exported .onnx of one or more objects; repeat "
                             "for several models (default: the demo model dope_hope/assets/demo_lite.pt when "
                             "this installation has it)")
    parser.add_argument("--classes", nargs="+", metavar="CLASS",
                        help="report only these objects of the model(s) (default: all)")
    cam = parser.add_argument_group("camera (default: the image's sibling annotation)")
    cam.add_argument("--camera", type=Path, metavar="K.json|YAML",
                     help="camera intrinsics file, or a ROS camera_info YAML (formats above)")
    for name in ("fx", "fy", "cx", "cy"):
        cam.add_argument(f"--{name}", type=positive_float if name in ("fx", "fy") else finite_float,
                         metavar="PX", help=f"{name}, pixels (give all four)")
    dep = parser.add_argument_group("depth refinement: line search (-LS), ICP")
    dep.add_argument("--depth", metavar="PATH|auto",
                     help="depth image registered to the (single) input image, or 'auto' for each "
                          "image's annotated depth (a RealSense brings its own)")
    dep.add_argument("--depth-scale", type=positive_float, metavar="MM_PER_UNIT",
                     help="millimetres per depth unit (default: the annotation's, else 1.0)")
    dep.add_argument("--depth-calibration", type=positive_float, default=1.0, metavar="F",
                     help="multiply depth by F, for raw captures of a camera with a known depth "
                          "scale error (default 1; HOPE's depth images are already corrected)")
    dep.add_argument("--icp", action="store_true",
                     help="after the line search, refine rotation and translation by ICP against the "
                          "depth (needs depth, and --mesh unless the object is a catalog box)")
    stream = parser.add_argument_group("video and cameras")
    stream.add_argument("--realtime", action="store_true",
                        help="play a video file (or recording) at its frame rate, dropping the frames the "
                             "loop cannot keep up with (as a live camera); default: every frame")
    stream.add_argument("--max-frames", type=positive_int, metavar="N", help="stop after N frames of the stream")
    stream.add_argument("--show", action="store_true",
                        help="show the overlays in a window (where a display exists; q quits)")
    stream.add_argument("--capture-size", type=_size, metavar="WxH",
                        help="resolution asked of a camera (default: the camera file's, else the "
                             "device's; RealSense 640x480)")
    stream.add_argument("--capture-fps", type=positive_float, metavar="FPS",
                        help="frame rate asked of a camera (RealSense default 30)")
    stream.add_argument("--track", action="store_true",
                        help="track the objects: stable track ids, smoothed poses (R, t) with the "
                             "frame's own in R_detected / t_detected, a missed object's predicted pose "
                             "(tracked: coasted) for a few frames; settings: the tracking section, e.g. "
                             "--set tracking.reprojection_px=2.0")
    stream.add_argument("--foxglove", nargs="?", const=DEFAULT_FOXGLOVE_PORT, type=_port, metavar="PORT",
                        help="serve the results live to the Foxglove app on ws://127.0.0.1:PORT (default "
                             f"{DEFAULT_FOXGLOVE_PORT}; 0: a free port; a file waits for the app to subscribe)")
    rec = parser.add_argument_group("robot recordings: ROS 1 .bag, ROS 2 bag folder, .mcap, .db3")
    rec.add_argument("--image-topic", metavar="TOPIC", help="colour image topic (default: the only one)")
    rec.add_argument("--depth-topic", metavar="TOPIC|none",
                     help="depth topic registered to colour (default: the only one, aligned_depth_to_color "
                          "preferred; none: no depth)")
    rec.add_argument("--camera-info-topic", metavar="TOPIC",
                     help="colour CameraInfo topic (default: the image topic's sibling camera_info)")
    rec.add_argument("--sync-tolerance", type=positive_float, metavar="MS",
                     help="largest colour-to-depth header stamp difference "
                          f"(default {DEFAULT_SYNC_TOLERANCE_S * 1000:g} ms)")
    rec.add_argument("--list-topics", action="store_true", help="print the recording's topics and the chosen ones, then stop")
    parser.add_argument("--mesh", action="append", type=Path, metavar="[NAME=]PATH",
                        help="object mesh: NAME=PATH per object (repeat; any models), one per --weights "
                             "(same order; one-object models), or one models folder holding "
                             "obj_NNNNNN.ply / CLASS/textured.obj / CLASS.obj / CLASS.ply: its box and "
                             "surface replace the cuboid (default: the checkpoint's cuboid); without "
                             "--weights, each file (or the folder's each mesh) is a new object the "
                             "pretrained start detects")
    parser.add_argument("--mesh-units", action="append", default=[], metavar="[NAME=]UNIT",
                        help="unit of the mesh files, m, cm or mm (default: .obj cm, .ply mm); NAME=UNIT "
                             "for one object's mesh (repeat; objects of mixed units)")
    _add_new_object_arguments(parser)
    parser.add_argument("--out", type=Path, default=Path("infer_out"), metavar="DIR",
                        help="folder for overlays and predictions.jsonl (default ./infer_out)")
    parser.add_argument("--no-overlay", action="store_true", help="do not write overlay images / video")
    parser.add_argument("--belief", action="store_true",
                        help="also write a montage of each object's belief maps (images only)")
    parser.add_argument("--backend", choices=("auto", "torch", "onnx"), default="auto",
                        help="auto: onnxruntime for .onnx files, PyTorch otherwise")
    parser.add_argument("--height", type=working_side, metavar="H",
                        help="network working height, pixels (default: the model's training scale; "
                             "400 for official DOPE weights)")
    parser.add_argument("--min-score", type=finite_float, metavar="S",
                        help="drop detections whose pose score is lower, for every object (default: each "
                             "object's own threshold when its file records one (train, dope-hope calibrate), else the "
                             "model's own, as the shipped demo model records, else "
                             f"{_default_min_score():g} from dope_hope/configs/infer.yaml; bench/RESULTS.md); "
                             "0 keeps all; the option min_score")
    parser.add_argument("--pose-search", choices=("hypotheses", "groups"),
                        help="hypotheses (default): candidate corner peaks + multi-hypothesis PnP; "
                             "groups: DOPE's one corner per type (faster, finds fewer)")
    add_settings_arguments(parser, "infer")
    add_preset_arguments(parser, "default --accurate for images and folders, --fast for video, cameras and recordings")
    parser.add_argument("--device", type=fixed_device, default="cpu", help="torch device (cpu, cuda, cuda:1)")
    parser.add_argument("--threads", type=positive_int, help="CPU threads for the network")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _add_new_object_arguments(parser: argparse.ArgumentParser) -> None:
    """The options of new objects the pretrained start detects (--mesh FILE, no --weights)."""
    start = parser.add_argument_group("new objects with no training (--mesh [NAME=]FILE, repeatable, no --weights)")
    start.add_argument("--up-axis", action="append", default=[], metavar="[NAME=]AXIS",
                       help="a new object's mesh: the mesh axis that is its vertical axis, as the pretrained "
                            "start learned y for cans and bottles: x, y (default), z, or =-x, =-y, =-z "
                            "(--up-axis=-z); NAME=AXIS for one object's mesh (repeat)")
    start.add_argument("--start", type=Path, metavar="W",
                       help="a new object's mesh: the start to run (default: the shipped "
                            "dope_hope/assets/pretrained_lite.pt)")


# ----------------------------------------------------------------------------- setup
def _global_camera(args: argparse.Namespace):
    """The camera of every input from --camera or --fx --fy --cx --cy (None: each image's own)."""
    from dope_hope.geometry import intrinsics_matrix
    from dope_hope.io.camera import ImageCamera, read_camera_file

    given = [getattr(args, k) for k in ("fx", "fy", "cx", "cy")]
    if args.camera is not None and any(v is not None for v in given):
        raise ConfigError("give either --camera or --fx --fy --cx --cy, not both")
    if args.camera is not None:
        return read_camera_file(args.camera)
    if any(v is not None for v in given):
        if any(v is None for v in given):
            raise ConfigError("--fx, --fy, --cx and --cy must be given together")
        return ImageCamera(K=intrinsics_matrix(*given), width=None, height=None, source=Path("--fx/--fy/--cx/--cy"))
    return None


def _note(message: str) -> None:
    print(f"dope-hope infer: {message}", file=sys.stderr)


def _warn(message: str) -> None:
    print(f"dope-hope infer: warning: {message}", file=sys.stderr, flush=True)


def inference_settings(args: argparse.Namespace) -> dict:
    """The inference options the command line sets: --config and --set (checked: one line naming
    the file or item and section.key), then the flags that name an option (--height,
    --min-score, --pose-search, --icp)."""
    given = given_settings("infer", args.config, args.overrides)
    flags = {"height": args.height, "min_score": args.min_score, "pose_search": args.pose_search,
             "icp": True if args.icp else None}
    given.update({k: v for k, v in flags.items() if v is not None})
    return given


def _predictors(args: argparse.Namespace, given: dict) -> list:
    """The predictors of --weights (the demo model by default), or the pretrained start's of
    each new object's --mesh (:func:`dope_hope.inference.model_choice.build_run_predictors`),
    with the options ``given`` (:func:`inference_settings`) over the run's preset."""
    from dope_hope.inference.model_choice import ModelChoice, build_run_predictors

    choice = ModelChoice(weights=tuple(args.weights or ()), meshes=tuple(args.mesh or ()), mesh_units=args.mesh_units,
                         up_axes=args.up_axis, start=args.start,
                         classes=None if args.classes is None else tuple(args.classes), backend=args.backend,
                         device=args.device, threads=args.threads)
    return build_run_predictors(choice, given, default_weights(), note=_note, preset=args.preset)


# ----------------------------------------------------------------------------- run
def run(args: argparse.Namespace) -> int:
    from dope_hope.geometry import UNIT_FLAG

    UNIT_FLAG.set("--mesh-units")  # named in the mesh unit hints

    from dope_hope.inference.options import STILL_IMAGE_PRESET, STREAM_PRESET
    from dope_hope.io.images import collect_images
    from dope_hope.io.paths import output_dir
    from dope_hope.io.streams import stream_kind

    given = inference_settings(args)  # read and checked once, before any work
    args.icp = given.get("icp") is True
    args.mesh_units = parse_mesh_units(args.mesh_units)  # [NAME=]UNIT values -> a unit or {NAME: unit}
    args.up_axis = parse_up_axes(args.up_axis)  # [NAME=]AXIS values -> an axis or {NAME: axis}
    if any(stream_kind(item) for item in args.inputs):
        args.preset = args.preset or STREAM_PRESET
        return _run_stream(args, given)
    args.preset = args.preset or STILL_IMAGE_PRESET
    stream_flags = [f"--{o.replace('_', '-')}" for o in STREAM_OPTIONS + RECORDING_OPTIONS
                    if getattr(args, o) not in (None, False)]
    if stream_flags:
        raise ConfigError(f"{', '.join(stream_flags)}: for a video or camera input, not images")
    if args.icp and args.depth is None:
        raise ConfigError("--icp refines against a depth image: give --depth PATH or --depth auto")
    images = collect_images(args.inputs)
    if args.depth not in (None, "auto") and len(images) != 1:
        raise ConfigError("--depth PATH applies to a single image; use --depth auto for several")
    from dope_hope.inference.image_inference import ImageOptions, check_output_names, predict_images

    if not args.no_overlay or args.belief:
        check_output_names(images)
    global_cam = _global_camera(args)
    out = output_dir(args.out)
    predictors = _predictors(args, given)
    options = ImageOptions(depth=args.depth, depth_scale_mm=args.depth_scale, depth_calibration=args.depth_calibration,
                           overlay=not args.no_overlay, belief=args.belief)
    result = predict_images(images, predictors, out, global_cam, options, progress=not args.no_progress,
                            on_record=lambda rec: print(json.dumps(rec), flush=True), warn=_warn)
    summary = (f"{len(images)} image(s), {len(result.records)} detection(s); predictions in "
               f"{out / 'predictions.jsonl'}" + (f", overlays in {out}" if result.overlays else ""))
    if result.skipped:
        path, exc = result.skipped[0]
        raise DopeHopeError(f"{len(result.skipped)} of {len(images)} image(s) skipped (first: {exc}); "
                            + (summary if result.done else "nothing written"))
    print(f"dope-hope infer: {summary}", file=sys.stderr)
    return 0


def _check_stream_flags(args: argparse.Namespace) -> None:
    """ConfigError for a flag that a stream of this kind cannot honour."""
    from dope_hope.io.streams import stream_kind

    kind = stream_kind(args.inputs[0]) if len(args.inputs) == 1 else None
    if args.icp and kind not in ("realsense", "recording"):
        raise ConfigError("--icp refines against a depth image: a video or an OpenCV camera has none "
                          "(a RealSense or a recording with depth has)")
    if args.realtime and kind not in ("video", "recording"):
        raise ConfigError("--realtime plays a file at its frame rate (cameras are live already)")
    given = [f"--{o.replace('_', '-')}" for o in RECORDING_OPTIONS if getattr(args, o) not in (None, False)]
    if given and kind != "recording":
        raise ConfigError(f"{', '.join(given)}: for a recording input (.bag, .mcap, .db3, ROS 2 bag folder)")
    if args.belief:
        raise ConfigError("--belief writes one montage per image; not for video or camera inputs")


def _stream_outputs(args: argparse.Namespace, out: Path, source, warn):
    """(overlay video or None, live window or None) of a stream."""
    from dope_hope.inference.image_inference import output_stem
    from dope_hope.io.streams import stream_kind
    from dope_hope.io.video import LiveWindow, OverlayVideo, display_problem

    video = window = None
    if not args.no_overlay and stream_kind(args.inputs[0]) != "recording":  # a recording's go to its MCAP
        video = OverlayVideo(out / f"{output_stem(source.name)}.overlay", source.fps or FALLBACK_FPS)
    if args.show:
        problem = display_problem()
        if problem is None:
            window = LiveWindow(f"dope-hope infer: {source.name}")
        else:
            warn(f"--show ignored: {problem}")
    return video, window


def _run_stream(args: argparse.Namespace, given: dict) -> int:
    """`run` for a video file, a camera, a RealSense or a recording (module docstring, "Streams"),
    with the inference options ``given``."""
    from dope_hope.inference.frame_loop import passive_openmp
    from dope_hope.io.paths import output_dir
    from dope_hope.io.predictions import write_predictions_jsonl

    _check_stream_flags(args)
    if args.list_topics:
        from dope_hope.ros.recordings import topic_table

        print(topic_table(args.inputs[0], args.image_topic, args.depth_topic, args.camera_info_topic))
        return 0
    source = _open_source(args)
    out = output_dir(args.out)
    video = window = ros = None
    try:
        passive_openmp()  # before torch is imported: its idle threads must not spin
        from dope_hope.inference.model_set import stream_tracker
        from dope_hope.inference.stream_inference import StreamSinks, predict_stream
        from dope_hope.ros.outputs import open_ros_outputs

        predictors = _predictors(args, given)
        video, window = _stream_outputs(args, out, source, _warn)
        ros = open_ros_outputs(out, source, args.foxglove, not args.no_overlay, _note)
        sinks = StreamSinks(on_record=lambda rec: print(json.dumps(rec), flush=True), video=video, window=window,
                            on_frame=None if ros is None else ros.on_frame)
        tracker = stream_tracker(predictors) if args.track else None
        result = predict_stream(source, predictors, sinks, tracker=tracker,
                                depth_calibration=args.depth_calibration, pace=args.realtime,
                                max_frames=args.max_frames, progress=not args.no_progress, warn=_warn)
        mcap = None if ros is None else ros.close()
        write_predictions_jsonl(out / "predictions.jsonl", result.records)
        video_path = None if video is None else video.close()
    except BaseException:
        for output in (video, ros):
            if output is not None:
                output.discard()
        raise
    finally:
        source.close()
        if window is not None:
            window.close()
    summary = (f"{source.name}: {result.stats.summary()}; {len(result.records)} detection(s); predictions in "
               f"{out / 'predictions.jsonl'}" + (f", overlay video {video_path}" if video_path else "")
               + (f", poses MCAP {mcap}" if mcap else ""))
    print(f"dope-hope infer: {summary}", file=sys.stderr)
    return 0


def _open_source(args: argparse.Namespace):
    """The stream's FrameSource: a recording (its topics, the --camera override) or open_stream's."""
    from dope_hope.io.streams import open_stream, stream_kind

    if stream_kind(args.inputs[0]) != "recording":
        return open_stream(args.inputs, _global_camera(args), args.depth, args.capture_size, args.capture_fps, _warn)
    from dope_hope.ros.recordings import open_recording

    tolerance_s = DEFAULT_SYNC_TOLERANCE_S if args.sync_tolerance is None else args.sync_tolerance / 1000.0
    return open_recording(args.inputs, args.image_topic, args.depth_topic, args.camera_info_topic,
                          _global_camera(args), args.depth, tolerance_s, args.icp, _warn)
