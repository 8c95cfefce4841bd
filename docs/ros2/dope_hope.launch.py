"""Launch `dope-hope ros2` from a ROS 2 installation (`ros2 launch`), with its parameters file
and the camera topics remapped (docs/commands/ros2.md).

    ros2 launch docs/ros2/dope_hope.launch.py
    ros2 launch docs/ros2/dope_hope.launch.py params:=my_params.yaml image:=/cam/color/image_raw \
        camera_info:=/cam/color/camera_info depth:=/cam/aligned_depth_to_color/image_raw

`dope-hope` must be on PATH (pip install "dope-hope[ros2]" in the Python that ros2 launch runs,
or a virtual environment's bin/dope-hope named in DOPE_HOPE_COMMAND).
"""
import os
from pathlib import Path

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, ExecuteProcess
from launch.substitutions import LaunchConfiguration

ARGUMENTS = {
    "params": (str(Path(__file__).resolve().parent / "dope_hope_params.yaml"), "the node's parameters file"),
    "image": ("/camera/color/image_raw", "colour image topic (Image; image_transport:=compressed: its /compressed)"),
    "camera_info": ("/camera/color/camera_info", "the colour camera's CameraInfo topic"),
    "depth": ("/camera/aligned_depth_to_color/image_raw", "depth registered to colour (16UC1 mm or 32FC1 m)"),
    "namespace": ("/", "the node's namespace (its outputs: NAMESPACE/dope_hope/...)"),
}


def generate_launch_description() -> LaunchDescription:
    command = os.environ.get("DOPE_HOPE_COMMAND", "dope-hope")
    remaps = [arg for name in ("image", "camera_info", "depth") for arg in ("-r", [f"{name}:=", LaunchConfiguration(name)])]
    node = ExecuteProcess(
        cmd=[command, "ros2", "--ros-args", "--params-file", LaunchConfiguration("params"), *remaps,
             "-r", ["__ns:=", LaunchConfiguration("namespace")]],
        output="screen", sigterm_timeout="30")
    return LaunchDescription([*(DeclareLaunchArgument(name, default_value=default, description=text)
                                for name, (default, text) in ARGUMENTS.items()), node])
