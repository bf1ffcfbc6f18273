"""Sensor models: every measurement becomes world-frame rays in metres (docs/method.md 2)."""

# its public modules; none is imported here, so `import virus_nerf.sensors` loads nothing else
__all__ = ["camera", "geometry", "irs", "rays", "rig", "uss"]
