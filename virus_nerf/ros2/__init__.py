"""A live ROS 2 node over DDS (cyclonedds), no ROS install: message types, transport, playback, the node."""

__all__ = ["command", "dds", "node", "play", "types"]
