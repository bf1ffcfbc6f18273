"""The simulator (docs/method.md 5): exact rooms from primitives, a robot drive and the robot's sensors,
written as an ETHZ-format recording. Entry point: `virus_nerf.sim.command.simulate`."""
