"""ROS 2 from the pip wheels (dope_hope/ros/ros2_runtime.py): the extra named where rclpy is
missing, the wheels' library folders found, a middleware that is not installed refused."""
from __future__ import annotations

import pytest

from dope_hope import cli
from dope_hope.errors import ConfigError
from dope_hope.ros import ros2_runtime


def test_without_the_extra_one_line_names_it(monkeypatch, capsys):
    monkeypatch.setattr(ros2_runtime, "rclpy_location", lambda: None)
    assert cli.main(["ros2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ['dope-hope ros2: error: the ROS 2 node needs rclpy and the ROS 2 message packages: '
                   'pip install "dope-hope[ros2]"']


def test_missing_library_folders_are_the_wheels_ones_not_on_the_path(tmp_path):
    for name in ("ros_rcl.libs", "ros_fastdds.libs", "other.libs"):
        (tmp_path / name).mkdir()
    found = ros2_runtime.wheel_library_dirs(tmp_path)
    assert [p for p in found if "ros_" in p] == [str(tmp_path / "ros_fastdds.libs"), str(tmp_path / "ros_rcl.libs")]
    env = {"LD_LIBRARY_PATH": str(tmp_path / "ros_rcl.libs")}
    assert str(tmp_path / "ros_rcl.libs") not in ros2_runtime.missing_library_dirs(tmp_path, env)
    assert str(tmp_path / "ros_fastdds.libs") in ros2_runtime.missing_library_dirs(tmp_path, env)


def test_a_middleware_that_is_not_installed_is_refused(tmp_path):
    ros2_runtime.check_rmw(tmp_path, {})  # unset: the wheels' own
    ros2_runtime.check_rmw(tmp_path, {"RMW_IMPLEMENTATION": ros2_runtime.WHEELS_RMW})
    with pytest.raises(ConfigError, match="RMW_IMPLEMENTATION=rmw_cyclonedds_cpp: that middleware is not installed"):
        ros2_runtime.check_rmw(tmp_path, {"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp", "LD_LIBRARY_PATH": ""})
    (tmp_path / "lib").mkdir()
    (tmp_path / "lib" / "librmw_cyclonedds_cpp.so").write_bytes(b"")
    ros2_runtime.check_rmw(tmp_path, {"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp",
                                      "LD_LIBRARY_PATH": str(tmp_path / "lib")})
