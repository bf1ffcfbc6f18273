"""VIRUS-NeRF: Vision, InfraRed and UltraSonic based Neural Radiance Fields.

Data flow (docs/method.md 2): data -> sensors -> sampler -> grid -> render (marching, compositing)
-> field -> losses -> trainer -> evaluation -> cli.
"""

import os as _os

__version__ = "0.1.0"

# Threads that spin while waiting steal whole time slices from the other pool (torch's and
# numba's OpenMP) on a 2-core CPU: passive waiting made a training step 1.5-1.9x faster
# (docs/method.md 10). Must be set before torch is imported; a user's own setting wins.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
