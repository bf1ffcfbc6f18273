"""ROS 1 / ROS 2 bags: reading, one decoder per message kind, import into the ETHZ layout
(`import-bag`), the live stream's frame pairing and pose sources, and writing bags."""

# its public modules; none is imported here, so `import virus_nerf.data.bags` loads nothing else
__all__ = ["command", "importer", "kiss_worker", "live", "messages", "odometry", "poses", "reader", "report", "stack_writer",
           "stages", "sync", "topics", "writer"]
