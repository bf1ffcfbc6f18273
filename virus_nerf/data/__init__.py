"""Reading and writing recordings in the ETHZ format (docs/method.md 4)."""

# its public modules; none is imported here, so `import virus_nerf.data` loads nothing else
__all__ = [
    "bags", "csvtable", "ethz", "frame", "images", "pcd", "playback", "room_box", "split",
    "voxel_map", "writer",
]
