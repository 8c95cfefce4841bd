"""ROS 2 from pip wheels in this process: ``rclpy`` importable, its C libraries found, the
middleware the wheels ship chosen.

The wheels (``pip install "dope-hope[ros2]"``: ros-rclpy, ros-rmw-fastrtps-cpp, the message
packages) keep their shared libraries in ``site-packages/ros_*.libs`` folders that the
dynamic loader only finds through ``LD_LIBRARY_PATH``, which it reads once, when a process
starts. Their bootstrapper (a ``.pth`` file) re-executes Python with the variable set; it does
not run under ``python -S``, looks only in ``sys.prefix``'s site-packages (not a ``--user`` or
``--target`` install) and trusts its marker variable even where the path was reset since (sudo,
``env -u``). :func:`prepare_ros2_process` does the same from where ``rclpy`` actually is,
once (a marker stops a loop), and sets ``RMW_IMPLEMENTATION`` to the wheels' Fast DDS when the
environment names none; a middleware named there whose library no folder holds is refused
with one line (a ROS install's environment sourced over the wheels).
"""
from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

from dope_hope.errors import ConfigError

#: How a user gets the ROS 2 node's packages.
ROS2_EXTRA_HINT = 'pip install "dope-hope[ros2]"'
#: The middleware the wheels ship (ros-rmw-fastrtps-cpp).
WHEELS_RMW = "rmw_fastrtps_cpp"
#: Set in the environment of the process re-executed with the library path (no second re-exec).
REEXEC_MARKER = "DOPE_HOPE_ROS2_LIBRARY_PATH_SET"


def rclpy_location() -> Path | None:
    """The site-packages folder holding ``rclpy``, or None where it is not installed."""
    spec = importlib.util.find_spec("rclpy")
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(list(spec.submodule_search_locations)[0]).parent


def wheel_library_dirs(site_packages: Path) -> list[str]:
    """The wheels' shared-library folders (``ros_*.libs``) and the interpreter's ``lib``, in a stable order."""
    dirs = sorted(str(p) for p in site_packages.glob("ros_*.libs") if p.is_dir())
    return dirs + [str(Path(sys.prefix) / "lib")]


def missing_library_dirs(site_packages: Path, env: dict[str, str]) -> list[str]:
    """The wheel folders ``LD_LIBRARY_PATH`` of ``env`` lacks."""
    present = set(filter(None, env.get("LD_LIBRARY_PATH", "").split(os.pathsep)))
    return [d for d in wheel_library_dirs(site_packages) if d not in present]


def check_rmw(site_packages: Path, env: dict[str, str]) -> None:
    """ConfigError naming RMW_IMPLEMENTATION when it names a middleware no library folder holds."""
    rmw = env.get("RMW_IMPLEMENTATION")
    if not rmw or rmw == WHEELS_RMW:
        return
    folders = wheel_library_dirs(site_packages) + env.get("LD_LIBRARY_PATH", "").split(os.pathsep)
    if not any(folder and Path(folder, f"lib{rmw}.so").is_file() for folder in folders):
        raise ConfigError(f"RMW_IMPLEMENTATION={rmw}: that middleware is not installed here (the ROS 2 wheels ship "
                          f"{WHEELS_RMW}); unset RMW_IMPLEMENTATION or install {rmw}")


def prepare_ros2_process() -> None:
    """Make ``rclpy`` usable in this process (module docstring): ConfigError naming the extra
    where it is not installed; the process re-executed once with the wheels' library folders
    on ``LD_LIBRARY_PATH`` where they are missing; ``RMW_IMPLEMENTATION`` set to the wheels'
    middleware where unset. Call before importing rclpy."""
    site = rclpy_location()
    if site is None:
        raise ConfigError(f"the ROS 2 node needs rclpy and the ROS 2 message packages: {ROS2_EXTRA_HINT}")
    env = dict(os.environ)
    check_rmw(site, env)
    os.environ.setdefault("RMW_IMPLEMENTATION", WHEELS_RMW)
    missing = missing_library_dirs(site, env)
    if missing and not env.get(REEXEC_MARKER):
        env["LD_LIBRARY_PATH"] = os.pathsep.join(missing + [p for p in env.get("LD_LIBRARY_PATH", "").split(os.pathsep)
                                                            if p])
        env[REEXEC_MARKER] = "1"
        env["RMW_IMPLEMENTATION"] = os.environ["RMW_IMPLEMENTATION"]
        sys.stdout.flush()
        sys.stderr.flush()
        os.execve(sys.executable, list(sys.orig_argv), env)  # the loader reads LD_LIBRARY_PATH at start only


def import_rclpy():
    """``rclpy`` with its C extension loaded; ConfigError (one line) where the libraries do not load."""
    try:
        import rclpy  # noqa: PLC0415 (rclpy is the optional ros2 extra, its libraries checked here)
        from rclpy.impl.implementation_singleton import rclpy_implementation  # noqa: F401, PLC0415 (the optional ros2 extra: its C libraries)
    except ImportError as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ConfigError(f"rclpy cannot load its libraries ({first}); reinstall with {ROS2_EXTRA_HINT}") from None
    return rclpy
