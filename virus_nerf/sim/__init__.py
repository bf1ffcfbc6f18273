"""The simulator (docs/method.md 5): exact rooms from primitives, a robot drive and the robot's sensors,
written as an ETHZ-format recording. Entry point: `virus_nerf.sim.command.simulate`."""

# its public modules; none is imported here, so `import virus_nerf.sim` loads nothing else
__all__ = [
    "command", "furniture", "kernels", "racks", "rooms", "scene", "sensors", "trajectory",
]
