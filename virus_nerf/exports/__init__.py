"""`virus-nerf export`: a trained run as files robotics tools read (README, "Exports").

(the 2D maps, the observed mask and the ESDF live in maps/, shared with the engine)
grid3d: the 3D VIRUS grid as .npy + JSON sidecar
clouds: PCD (pypcd4) and PLY writers
views: what the model renders at poses (360 deg scans, dense surface cloud, colour/depth images)
command: the command itself (flags, checks, output folder)
"""

# its public modules; none is imported here, so `import virus_nerf.exports` loads nothing else
__all__ = ["clouds", "command", "grid3d", "views"]
