"""VIRUS-NeRF: Vision, InfraRed and UltraSonic based Neural Radiance Fields.

Data flow (docs/method.md 2): data -> sensors -> sampler -> grid -> render (marching, compositing)
-> field -> losses -> trainer -> evaluation -> cli.
"""

__version__ = "0.1.0"

# No OpenMP settings on import: the runtime's default (spin briefly, then sleep) trains 1.4x faster
# than OMP_WAIT_POLICY=PASSIVE when the run has the cores to itself; runs that share the CPU
# (experiments with several workers) get PASSIVE from their launcher (docs/method.md 10).
