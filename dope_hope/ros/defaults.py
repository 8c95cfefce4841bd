"""The ROS package's defaults, one owner each: the recordings' reader and the live Foxglove
server take them as their own, and `dope-hope infer` quotes them in its options. Plain
numbers in a module of their own, so that building `--help` imports neither numpy nor
rosbags."""
from __future__ import annotations

#: Largest colour-to-depth header stamp difference of a recording's pair, seconds (half a
#: 30 fps frame is 16.7 ms).
DEFAULT_SYNC_TOLERANCE_S = 0.015
#: Port of the live Foxglove WebSocket server, the app's default (`infer --foxglove` without a
#: value).
DEFAULT_FOXGLOVE_PORT = 8765
