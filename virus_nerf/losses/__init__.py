"""Training losses (docs/method.md 3.2)."""

from virus_nerf.losses.terms import (
    LossTerms,
    LossWeights,
    colour_loss,
    depth_loss,
    distortion_loss,
    free_space_loss,
    line_of_sight_terms,
    stereo_free_until,
    total_loss,
    uss_loss,
    weighted_depth_loss,
)

__all__ = ["LossTerms", "LossWeights", "colour_loss", "depth_loss", "distortion_loss", "free_space_loss", "line_of_sight_terms", "stereo_free_until", "total_loss", "uss_loss", "weighted_depth_loss"]
