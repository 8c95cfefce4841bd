"""Run the pose estimator as a live ROS 2 node (pip install "dope-hope[ros2]"; no ROS install).

Examples:
  dope-hope ros2                                              (the demo model, a RealSense's topics)
  dope-hope ros2 --ros-args -p weights:=ketchup.pt -p min_score:=0.3
  dope-hope ros2 --ros-args -r image:=/cam/image_raw -r camera_info:=/cam/camera_info -p use_depth:=false
  dope-hope ros2 --ros-args --params-file docs/commands/ros2_params.yaml
  dope-hope ros2 --set decode.threshold=0.2 --ros-args -p mesh:="[meshes/]" -p icp:=true
  ros2 param set /dope_hope min_score 0.6                      (while it runs; classes too)

Subscribes (sensor-data QoS; -p input_reliability:=reliable for large raw images): image (sensor_msgs/Image; CompressedImage on image/compressed
with -p image_transport:=compressed), camera_info (each image paired with the camera info of
its own stamp) and the aligned depth (16UC1 mm or 32FC1 m, paired by stamp within
depth_tolerance_ms; -p use_depth:=false: none). Unremapped, a RealSense's names:
camera/color/image_raw, camera/color/camera_info, camera/aligned_depth_to_color/image_raw.

Publishes on each processed image's stamp and frame_id, in the node's namespace (/dope_hope/):
poses (PoseArray), pose_CLASS (PoseStamped, each class's best), markers (MarkerArray),
overlay (Image), processing_time_ms (Float64) and, where vision_msgs is installed,
detections (Detection3DArray). When inference falls behind, the newest frame wins: older
ones are dropped and counted. Ctrl-C ends it (exit 0) with a summary line.

Parameters: weights, mesh, mesh_units, up_axis, start, classes, backend, device, threads,
image_transport, input_reliability, use_depth, depth_tolerance_ms, depth_wait_ms, depth_calibration, track,
overlay, and every inference setting under its --set name (min_score, height, icp,
decode.threshold, ...: `dope-hope settings infer`); min_score and classes change at run time.
Full reference: docs/commands/ros2.md.
"""
from __future__ import annotations

import argparse
import sys

from dope_hope.commands.settings import add_settings_arguments, given_settings


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    add_settings_arguments(parser, "infer", config_help="inference settings file (YAML, only the keys it changes; "
                                                        "`dope-hope settings infer` prints them all); ROS "
                                                        "parameters of the same names win")
    parser.add_argument("--ros-args", nargs=argparse.REMAINDER, dest="ros_args", default=[], metavar="ARG",
                        help="ROS arguments, to the end: -p NAME:=VALUE, -r FROM:=TO, --params-file FILE, "
                             "-r __ns:=/robot, --log-level debug")


def run(args: argparse.Namespace) -> int:
    from dope_hope.ros.ros2_runtime import import_rclpy, prepare_ros2_process

    base = given_settings("infer", args.config, args.overrides)  # checked before any work
    prepare_ros2_process()
    rclpy = import_rclpy()
    from rclpy.executors import ExternalShutdownException

    from dope_hope.inference.frame_loop import passive_openmp

    passive_openmp()  # before torch: its idle threads must not take the cores of decoding and transport
    from dope_hope.ros.node import DopeHopeNode

    rclpy.init(args=["dope-hope", "--ros-args", *args.ros_args])
    node = None
    try:
        node = DopeHopeNode(base_settings=base)
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            node.close()
            print(f"dope-hope ros2: {node.summary()}", file=sys.stderr, flush=True)
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
