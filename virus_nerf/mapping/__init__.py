"""Mapping while driving: replaying a recording (or a bag) through a `engine.mapper.Mapper` in real
time, with map snapshots on the way (`virus-nerf map-bag`)."""

# its public modules; none is imported here, so `import virus_nerf.mapping` loads nothing else
__all__ = ["command", "live_view", "options", "replay", "ros_maps", "stream"]
