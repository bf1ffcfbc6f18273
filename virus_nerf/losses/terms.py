"""Training losses (paper eq. 3, 5, 6, 7; docs/method.md 3.2), pure functions on per-ray tensors.

Every depth loss is a mean over the rays where its sensor has a valid value (NaN = invalid), in
metres squared, never over all rays, so the weights do not depend on the room size or on how
many rays of a batch come from which sensor. With no valid ray a loss is exactly 0 with a zero
(not NaN) gradient: invalid targets are replaced before any arithmetic, because
`where(mask, (p - NaN)^2, 0)` would still send NaN into the backward pass.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from virus_nerf.losses.weights import LossWeights


def _masked_mean(values: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Mean of values (R,) over valid (R,) bool; 0 (with zero gradient) when nothing is valid."""
    total = torch.where(valid, values, torch.zeros_like(values)).sum()
    return total / valid.sum().clamp_min(1).to(values.dtype)


def colour_loss(pred_rgb: torch.Tensor, target_rgb: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean squared error of RGB in [0, 1]: pred (R, 3), target (R, 3), mask (R,) bool or None.

    Mean over the selected rays and the 3 channels; 0 when the mask selects nothing.
    """
    if pred_rgb.shape != target_rgb.shape or pred_rgb.shape[-1] != 3:
        raise ValueError(f"colour_loss: pred {tuple(pred_rgb.shape)} and target {tuple(target_rgb.shape)} must both be (R, 3)")
    valid = torch.ones(pred_rgb.shape[0], dtype=torch.bool, device=pred_rgb.device) if mask is None else mask
    target = torch.where(valid[:, None], target_rgb, pred_rgb.detach())
    per_ray = ((pred_rgb - target) ** 2).mean(dim=-1)  # (R,)
    return _masked_mean(per_ray, valid)


def depth_loss(pred_depth: torch.Tensor, target_depth: torch.Tensor) -> torch.Tensor:
    """Squared depth error (m^2), mean over rays with a finite target: pred (R,), target (R,) m.

    Used for the IRS zones (eq. 6) and the RGB-D ablation; target NaN = no measurement.
    """
    _check_same(pred_depth, target_depth, "depth_loss")
    valid = torch.isfinite(target_depth)
    target = torch.where(valid, target_depth, pred_depth.detach())
    return _masked_mean((pred_depth - target) ** 2, valid)


def weighted_depth_loss(pred_depth: torch.Tensor, target_depth: torch.Tensor, sigma: torch.Tensor,
                        sigma_ref: float) -> torch.Tensor:
    """Squared depth error (m^2) of targets with known noise, mean over rays with a finite target.

    pred, target, sigma (R,) m. Each ray's error counts with weight 1 / (1 + (sigma /
    sigma_ref)^2): a target as precise as sigma_ref or better counts (nearly) fully, a noisy
    one in proportion to its inverse variance, so a far triangulated point cannot pull as hard
    as a near one.
    """
    _check_same(pred_depth, target_depth, "weighted_depth_loss")
    valid = torch.isfinite(target_depth) & torch.isfinite(sigma)
    target = torch.where(valid, target_depth, pred_depth.detach())
    weight = torch.where(valid, 1.0 / (1.0 + (sigma / sigma_ref) ** 2), torch.zeros_like(sigma))
    return _masked_mean(weight * (pred_depth - target) ** 2, valid)


def uss_loss(pred_depth: torch.Tensor, echo_range: torch.Tensor, eps: float = 0.03) -> torch.Tensor:
    """One-sided USS loss (eq. 7): nothing may render closer than the echo.

    pred (R,) m, echo (R,) m (NaN = no echo or ray outside the cone). Per ray
    (D - D_uss)^2 where D < D_uss - eps, else 0; averaged over the rays with a valid echo.
    """
    _check_same(pred_depth, echo_range, "uss_loss")
    valid = torch.isfinite(echo_range)
    echo = torch.where(valid, echo_range, pred_depth.detach())
    in_front = valid & (pred_depth.detach() < echo - eps)
    per_ray = torch.where(in_front, (pred_depth - echo) ** 2, torch.zeros_like(pred_depth))
    return _masked_mean(per_ray, valid)


def distortion_loss(weights: torch.Tensor, t_starts: torch.Tensor, t_ends: torch.Tensor,
                    ray_offsets: torch.Tensor) -> torch.Tensor:
    """Mean over rays of the interval distortion of mip-NeRF 360 (Barron et al. 2022), in metres.

    Per ray: sum_ij w_i w_j |m_i - m_j| + 1/3 sum_i w_i^2 d_i, with m the interval midpoints and
    d their lengths. Small when a ray's weight sits in one short stretch (one surface), large
    when it is spread along the ray (floaters in front of a wall). Packed samples sorted by ray
    and distance: weights, t_starts, t_ends (S,), ray_offsets (R + 1,). The double sum is
    2 sum_i w_i (m_i W_i - M_i) with W_i, M_i the sums of w and w m over the ray's samples
    before i (exclusive prefix sums, taken globally and rebased at each ray's first sample).
    """
    n_rays = ray_offsets.shape[0] - 1
    if weights.numel() == 0:
        return weights.sum() * 0.0
    w = weights.to(torch.float64)
    m = ((t_starts + t_ends) * 0.5).to(torch.float64)
    d = (t_ends - t_starts).to(torch.float64)
    counts = ray_offsets[1:] - ray_offsets[:-1]  # (R,)
    ray = torch.repeat_interleave(torch.arange(n_rays, device=w.device), counts)  # (S,)
    start = ray_offsets[:-1][ray]  # (S,) first sample of each sample's ray

    def exclusive_in_ray(x: torch.Tensor) -> torch.Tensor:
        c = torch.cumsum(x, 0) - x  # global exclusive prefix sum
        return c - c[start]

    inter = 2.0 * (w * (m * exclusive_in_ray(w) - exclusive_in_ray(w * m))).sum()
    intra = (w * w * d).sum() / 3.0
    return ((inter + intra) / max(1, n_rays)).to(weights.dtype)


def free_space_loss(weights: torch.Tensor, t_ends: torch.Tensor, ray_offsets: torch.Tensor,
                    free_until: torch.Tensor) -> torch.Tensor:
    """Line-of-sight emptiness (Urban Radiance Fields' "empty" term): mean over rays with a finite
    `free_until` of sum_i w_i^2 over the samples that end before it.

    A range sensor that saw its first return at r says the space in front of it is empty; the
    expected-depth losses see only the weighted mean of a ray, so a floater in front of a wall
    can hide behind a far tail. weights, t_ends (S,) packed by ray (ray_offsets (R + 1,)),
    free_until (R,) m (NaN = no evidence on that ray).
    """
    n_rays = ray_offsets.shape[0] - 1
    valid = torch.isfinite(free_until)
    if weights.numel() == 0 or not bool(valid.any()):
        return weights.sum() * 0.0
    counts = ray_offsets[1:] - ray_offsets[:-1]  # (R,)
    ray = torch.repeat_interleave(torch.arange(n_rays, device=weights.device), counts)  # (S,)
    limit = torch.where(valid, free_until, torch.full_like(free_until, -1.0))[ray]  # (S,)
    before = t_ends < limit
    per_ray = torch.zeros(n_rays, dtype=weights.dtype, device=weights.device)
    per_ray = per_ray.index_add(0, ray, torch.where(before, weights * weights, torch.zeros_like(weights)))
    return _masked_mean(per_ray, valid)


def stereo_free_until(ranges: torch.Tensor, sigmas: torch.Tensor, short: float, margin: float) -> torch.Tensor:
    """(R,) m along each ray up to which a stereo target (range, sigma (R,) m; NaN: none) says
    space is empty: `short` of its range before it, and at least max(margin, 2 sigma) before it.
    A share rather than a fixed margin because a triangulated point's error grows with its range
    and a far target's ray grazes more of what lies near it."""
    return ranges * (1.0 - short) - torch.clamp(2.0 * sigmas, min=margin)


def line_of_sight_terms(weights: LossWeights, sample_weights: torch.Tensor, t_ends: torch.Tensor,
                        ray_offsets: torch.Tensor, uss_range: torch.Tensor | None = None,
                        stereo_range: torch.Tensor | None = None,
                        stereo_sigma: torch.Tensor | None = None) -> torch.Tensor:
    """free_uss * free_space_loss before the USS echoes (free_margin m short of the echo), plus
    free_stereo * free_space_loss before the stereo targets (`stereo_free_until`); None: that
    sensor's term is off."""
    total = sample_weights.sum() * 0.0
    if weights.free_uss > 0 and uss_range is not None:
        total = total + weights.free_uss * free_space_loss(sample_weights, t_ends, ray_offsets,
                                                           uss_range - weights.free_margin)
    if weights.free_stereo > 0 and stereo_range is not None and stereo_sigma is not None:
        until = stereo_free_until(stereo_range, stereo_sigma, weights.free_stereo_short, weights.free_margin)
        total = total + weights.free_stereo * free_space_loss(sample_weights, t_ends, ray_offsets, until)
    return total


def _check_same(pred: torch.Tensor, target: torch.Tensor, name: str) -> None:
    if pred.shape != target.shape or pred.dim() != 1:
        raise ValueError(f"{name}: pred {tuple(pred.shape)} and target {tuple(target.shape)} must both be (R,)")


@dataclass(frozen=True)
class LossTerms:
    """Each weighted-sum term (unweighted value, scalar tensor) and the weighted total."""

    colour: torch.Tensor
    irs: torch.Tensor
    uss: torch.Tensor
    rgbd: torch.Tensor
    total: torch.Tensor
    distortion: torch.Tensor | None = None  # unweighted, when the term is on
    stereo: torch.Tensor | None = None  # unweighted, when the stereo sensor is trained
    line_of_sight: torch.Tensor | None = None  # weighted (`line_of_sight_terms`), when on

    def as_floats(self) -> dict[str, float]:
        """Plain floats for logging; a term that is off is 0.0, so that total = the weighted sum
        of the others plus line_of_sight."""
        return {k: 0.0 if getattr(self, k) is None else float(getattr(self, k).detach())
                for k in ("colour", "irs", "uss", "rgbd", "stereo", "distortion", "line_of_sight", "total")}


def total_loss(
    weights: LossWeights,
    pred_rgb: torch.Tensor,
    target_rgb: torch.Tensor,
    pred_depth: torch.Tensor,
    irs_depth: torch.Tensor | None = None,
    uss_range: torch.Tensor | None = None,
    rgbd_depth: torch.Tensor | None = None,
    rgb_mask: torch.Tensor | None = None,
    uss_eps: float = 0.03,
    stereo_depth: torch.Tensor | None = None,
    stereo_sigma: torch.Tensor | None = None,
) -> LossTerms:
    """L_tot = w_c L_c + w_irs L_irs + w_uss L_uss + w_rgbd L_rgbd (+ w_stereo L_stereo) over
    one batch of R rays.

    pred_rgb/target_rgb (R, 3), pred_depth (R,) m; each sensor target (R,) m with NaN on rays
    it does not cover, or None when the sensor is not trained (its term is then 0).
    """
    zero = torch.zeros((), dtype=pred_depth.dtype, device=pred_depth.device)
    lc = colour_loss(pred_rgb, target_rgb, rgb_mask)
    li = depth_loss(pred_depth, irs_depth) if irs_depth is not None else zero
    lu = uss_loss(pred_depth, uss_range, uss_eps) if uss_range is not None else zero
    lr = depth_loss(pred_depth, rgbd_depth) if rgbd_depth is not None else zero
    total = weights.colour * lc + weights.irs * li + weights.uss * lu + weights.rgbd * lr
    ls = None
    if stereo_depth is not None and stereo_sigma is not None:
        ls = weighted_depth_loss(pred_depth, stereo_depth, stereo_sigma, weights.stereo_sigma_ref)
        total = total + weights.stereo * ls
    return LossTerms(colour=lc, irs=li, uss=lu, rgbd=lr, total=total, stereo=ls)
