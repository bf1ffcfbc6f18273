"""A training step's loss, as pure functions of the config, the batch and the render (no Mapper
state): which rays learn colour, whether the stereo targets' line of sight trains, and the weighted
sum of docs/method.md 3.2 with the distortion and line-of-sight terms."""

from __future__ import annotations

import dataclasses

import torch

from virus_nerf.engine.config import MapperConfig
from virus_nerf.losses import LossTerms, distortion_loss, line_of_sight_terms, total_loss
from virus_nerf.sampler.batch import RayBatch
from virus_nerf.scene_box import SceneBox


def colour_rays(config: MapperConfig, batch: RayBatch) -> torch.Tensor | None:
    """(R,) bool: the rays that render and learn colour; None = all. With
    `density_only_depth_rays` the depth-supervised rays (IRS, RGB-D) train the density alone."""
    if not config.density_only_depth_rays:
        return None
    has_depth = torch.zeros(len(batch), dtype=torch.bool, device=batch.origins.device)
    if "irs" in config.sensors:
        has_depth |= torch.isfinite(batch.irs_range)
    if "rgbd" in config.sensors:
        has_depth |= torch.isfinite(batch.rgbd_range)
    return ~has_depth


def stereo_line_of_sight(config: MapperConfig, box: SceneBox, growing: bool, driving: bool) -> bool:
    """Whether the stereo targets' line-of-sight term trains (`weights.free_stereo`): the stereo
    sensor trained, offline (while driving it marked more obstacles near the path free), in a
    fitted box (a grown one's room size is not known when the drive starts) whose longest
    horizontal side is at most `weights.free_stereo_room_m` (docs/decisions.md D77)."""
    w = config.weights
    side = float(max(box.hi[0] - box.lo[0], box.hi[1] - box.lo[1]))
    return (w.free_stereo > 0 and "stereo" in config.sensors and not growing and not driving
            and side <= w.free_stereo_room_m)


def step_loss(config: MapperConfig, batch: RayBatch, out, samples, rgb_rays: torch.Tensor | None,
              stereo_free: bool = False) -> LossTerms:
    """A step's loss from its rays' targets (`batch`), the render (`out`: rgb, depth, weights)
    and its packed samples: the weighted sum of docs/method.md 3.2 over the sensors trained,
    then the distortion and the line-of-sight terms when their weights are on (the stereo
    targets' when `stereo_free`: `stereo_line_of_sight`). Pure: no state."""
    sensors, w = config.sensors, config.weights
    terms = total_loss(
        w,
        pred_rgb=out.rgb,
        target_rgb=batch.rgb,
        pred_depth=out.depth,
        irs_depth=batch.irs_range if "irs" in sensors else None,
        uss_range=batch.uss_range if "uss" in sensors else None,
        rgbd_depth=batch.rgbd_range if "rgbd" in sensors else None,
        rgb_mask=rgb_rays,
        stereo_depth=batch.stereo_range if "stereo" in sensors else None,
        stereo_sigma=batch.stereo_sigma if "stereo" in sensors else None,
    )
    if w.distortion > 0:
        ld = distortion_loss(out.weights, samples.t_starts, samples.t_ends, samples.ray_offsets)
        terms = dataclasses.replace(terms, total=terms.total + w.distortion * ld, distortion=ld)
    uss = batch.uss_range if w.free_uss > 0 and "uss" in sensors else None
    stereo = stereo_free and batch.stereo_range is not None
    if uss is not None or stereo:
        free = line_of_sight_terms(w, out.weights, samples.t_ends, samples.ray_offsets, uss_range=uss,
                                   stereo_range=batch.stereo_range if stereo else None,
                                   stereo_sigma=batch.stereo_sigma if stereo else None)
        terms = dataclasses.replace(terms, total=terms.total + free, line_of_sight=free)
    return terms
