"""Mapping while driving: replaying a recording (or a bag) through a `engine.mapper.Mapper` in real
time, with map snapshots on the way (`virus-nerf map-bag`)."""
