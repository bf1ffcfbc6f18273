"""Shared helpers: atomic writes and output folders, the user cache, seeding, the process clock,
kernel backend choice, memory checks, the numba slab test, clean stops, text files."""

# its public modules; none is imported here, so `import virus_nerf.utils` loads nothing else
__all__ = ["backend", "cache", "clock", "io", "memory", "parent", "seeding", "slab", "stop", "textfile"]
