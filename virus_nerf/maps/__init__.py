"""2D maps of a trained model, shared by the engine, the run layer and `export`.

scans: 2D scan geometry (Scan2D, fields of view, horizontal scan rays)
occupancy: map_server rasters (trinary scan map, scale probability map) and their files
observed: where some sensor looked; unknown elsewhere, whatever the model says
esdf: the 2D signed distance field of a map, for planners
extract: the one map extraction (positions, camera height, masks) used by every consumer
evidence: the IRS zones and USS cones as 2D rays (the sensors-only map, the planner's evidence)
planner: the planner's map: the scans, then IRS hits, stereo points and voted USS arcs
"""

# its public modules; none is imported here, so `import virus_nerf.maps` loads nothing else
__all__ = ["esdf", "evidence", "extract", "observed", "occupancy", "planner", "scans"]
