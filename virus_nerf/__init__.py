"""VIRUS-NeRF: Vision, InfraRed and UltraSonic based Neural Radiance Fields.

Data flow (design 2): data -> sensors -> sampler -> grid -> render (marching, compositing)
-> field -> losses -> trainer -> evaluation -> cli.
"""

__version__ = "0.1.0"
