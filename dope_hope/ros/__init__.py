"""Everything ROS in one package: robot recordings in and out, ROS 2 messages, the live Foxglove view (see ARCHITECTURE.md)."""
