"""`virus-nerf export`: a trained run as files robotics tools read (README, "Exports").

maps: 2D rasters in the ROS map_server convention (trinary scan map, Bayesian probability map)
grid3d: the 3D VIRUS grid as .npy + JSON sidecar
esdf: the 2D signed Euclidean distance field of the map, for planners
clouds: PCD (pypcd4) and PLY writers
views: what the model renders at poses (360 deg scans, dense surface cloud, colour/depth images)
command: the command itself (flags, checks, output folder)
"""
