"""Camera depth from the robot's own images and poses (sparse, triangulated; docs/method.md 3.7)."""

from virus_nerf.stereo.depth import StereoBuilder, StereoConfig, StereoDepth

__all__ = ["StereoBuilder", "StereoConfig", "StereoDepth"]
