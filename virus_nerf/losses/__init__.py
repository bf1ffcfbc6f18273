"""Training losses (docs/method.md 3.2).

The names below load on first use (PEP 562), so that `virus_nerf.losses.weights` (a run's
config, its flags, `train --help`) does not pull in torch."""

_LAZY = {name: "virus_nerf.losses.terms" for name in (
    "LossTerms", "colour_loss", "depth_loss", "distortion_loss", "free_space_loss", "line_of_sight_terms",
    "stereo_free_until", "total_loss", "uss_loss", "weighted_depth_loss")} | {"LossWeights": "virus_nerf.losses.weights"}
__all__ = ["LossTerms", "LossWeights", "colour_loss", "depth_loss", "distortion_loss", "free_space_loss",
           "line_of_sight_terms", "stereo_free_until", "total_loss", "uss_loss", "weighted_depth_loss"]


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
