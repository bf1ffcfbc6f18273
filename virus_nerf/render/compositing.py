"""Volume rendering of packed samples (docs/method.md 3.1, paper eq. 1, 2, 4).

Per ray, samples j = 1..M with density sigma_j, colour c_j, interval length delta_j, midpoint t_j:
    tau_j = sigma_j delta_j,  alpha_j = 1 - exp(-tau_j),  T_j = exp(-sum_{l<j} tau_l),
    w_j = T_j alpha_j,  A = sum_j w_j,  C = sum_j w_j c_j + (1 - A) b,  D = sum_j w_j t_j.
D is the paper's unnormalised depth (metres along the unit ray, biased short where A < 1);
`scan_depth` gives D / A for the 2D scans (docs/method.md 6.3), `opacity_front` the depth where
a ray's accumulated weight first reaches a level (the map's low rays, D94).

Backward (closed form used by the numba kernel). With upstream gradients g_C (3,), g_D, g_A per
ray and g_w per sample, the loss depends on w_j through
    e_j = g_w_j + g_C . (c_j - b) + g_D t_j + g_A,
and since dw_j/dtau_k = T_{k+1} for j = k, -w_j for j > k, 0 for j < k:
    dL/dtau_k = e_k T_{k+1} - sum_{j>k} e_j w_j,   dL/dsigma_k = delta_k dL/dtau_k,
    dL/dc_k = w_k g_C,   dL/db = (1 - A) g_C.
The suffix sum is the ray total minus a running prefix, so the backward is two passes per ray.

Early termination (`early_stop_eps` > 0): a sample contributes only while the transmittance in
front of it is T_j >= eps; later samples get w_j = 0 and no gradient. Both backends apply the
same rule to their float64 T, so they agree except when some T_j lies within ~1e-15 (relative) of
eps. eps = 0 (the default) renders every sample.

Both backends compute in float64 internally and return the dtype of `sigmas`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
import torch
from numba import prange

from virus_nerf.render.samples import PackedSamples
from virus_nerf.utils.backend import Backend, resolve_backend


@dataclass
class RenderOutput:
    """Per-ray renders of R rays and the per-sample weights of S samples."""

    rgb: torch.Tensor  # (R, 3) in [0, 1] for colours in [0, 1]
    depth: torch.Tensor  # (R,) metres, unnormalised: sum_j w_j t_j
    opacity: torch.Tensor  # (R,) accumulated weight A in [0, 1]
    weights: torch.Tensor  # (S,) w_j


def composite(
    sigmas: torch.Tensor,
    rgbs: torch.Tensor,
    samples: PackedSamples,
    n_rays: int,
    background: torch.Tensor | None = None,
    backend: Backend = "auto",
    early_stop_eps: float = 0.0,
) -> RenderOutput:
    """Render sigmas (S,) [1/m] and rgbs (S, 3) of packed samples; background (3,) or (R, 3).

    Differentiable w.r.t. sigmas, rgbs and background.
    """
    s = samples.n_samples
    if n_rays != samples.n_rays:
        raise ValueError(f"n_rays={n_rays} but the samples' ray_offsets describe {samples.n_rays}")
    if sigmas.shape != (s,) or rgbs.shape != (s, 3):
        raise ValueError(
            f"expected sigmas (S,) and rgbs (S, 3) with S={s}, got {tuple(sigmas.shape)} and "
            f"{tuple(rgbs.shape)}"
        )
    if background is not None and background.shape not in ((3,), (n_rays, 3)):
        raise ValueError(f"background must be (3,) or (R, 3), got {tuple(background.shape)}")
    if early_stop_eps < 0:
        raise ValueError(f"early_stop_eps must be >= 0, got {early_stop_eps}")
    which = resolve_backend(backend, sigmas, rgbs, samples.t_starts)
    if which == "torch":
        return _composite_torch(sigmas, rgbs, samples, n_rays, background, early_stop_eps)
    if background is None:
        background = torch.zeros(3, dtype=sigmas.dtype)
    rgb, depth, opacity, weights = _CompositeNumba.apply(
        sigmas,
        rgbs,
        background,
        samples.t_starts,
        samples.t_ends,
        samples.ray_offsets,
        float(early_stop_eps),
    )
    return RenderOutput(rgb=rgb, depth=depth, opacity=opacity, weights=weights)


def scan_depth(render: RenderOutput, min_opacity: float = 0.5) -> torch.Tensor:
    """(R,) metres: D / A where the opacity A >= min_opacity, else NaN (docs/method.md 3.1, 6.3)."""
    d = render.depth / render.opacity.clamp(min=1e-12)
    return torch.where(render.opacity >= min_opacity, d, torch.full_like(d, math.nan))


def opacity_front(render: RenderOutput, samples: PackedSamples, level: float, min_opacity: float = 0.5) -> torch.Tensor:
    """(R,) metres: where each ray's accumulated weight first reaches `level` (the start of the
    interval of the sample that takes it there), NaN where the opacity A < min_opacity. The near
    side of a surface, where D / A (`scan_depth`) lies inside a soft one; the map's low rays use it
    (maps/extract.py, D94). Pure function of the packed weights (S,) in march order; no gradient."""
    if not 0.0 < level <= 1.0:
        raise ValueError(f"level must be in (0, 1], got {level}")
    with torch.no_grad():
        w = render.weights.detach().to(torch.float64)  # (S,)
        incl = torch.cumsum(w, 0)  # (S,) global running sum
        before_ray = torch.cat([incl.new_zeros(1), incl])[samples.ray_offsets[:-1]]  # (R,) sum of earlier rays
        reached = incl - before_ray[samples.ray_indices] >= level  # (S,) the ray's own sum so far >= level
        front = torch.full((samples.n_rays,), math.inf, dtype=torch.float64, device=w.device)
        front.scatter_reduce_(0, samples.ray_indices[reached], samples.t_starts.to(torch.float64)[reached],
                              reduce="amin")
        seen = (render.opacity.detach() >= min_opacity) & torch.isfinite(front)
        return torch.where(seen, front, torch.full_like(front, math.nan)).to(render.depth.dtype)


# ----------------------------------------------------------------------------- torch twin


def _transmittance(tau: torch.Tensor, samples: PackedSamples) -> torch.Tensor:
    """T_j (S,) float64 from tau (S,) float64: segment-wise exclusive cumsum (global cumsum minus
    each ray's start), no loops."""
    incl = torch.cumsum(tau, 0)
    excl = torch.cat([incl.new_zeros(1), incl[:-1]])  # (S,) sum of all earlier samples
    first = samples.ray_offsets[:-1][samples.ray_indices]  # (S,) index of each sample's ray's first sample
    return torch.exp(-(excl - excl[first]))


def transmittance(sigmas: torch.Tensor, samples: PackedSamples) -> torch.Tensor:
    """T_j = exp(-sum_{l<j} sigma_l delta_l) (S,) float64 of packed samples; no gradient.

    For skipping samples that cannot matter (docs/method.md 3.1): every loss term and every
    gradient reaches sample j through w_j = T_j alpha_j or through later samples' T, so samples
    behind T_j < eps change renders and gradients by less than eps.
    """
    with torch.no_grad():
        delta = (samples.t_ends.to(torch.float64) - samples.t_starts.to(torch.float64))  # (S,)
        return _transmittance(sigmas.detach().to(torch.float64) * delta, samples)


def _composite_torch(sigmas, rgbs, samples, n_rays, background, eps):
    ri = samples.ray_indices
    ts = samples.t_starts.to(torch.float64)
    te = samples.t_ends.to(torch.float64)
    delta = te - ts  # (S,)
    tm = (ts + te) * 0.5
    tau = sigmas.to(torch.float64) * delta
    trans = _transmittance(tau, samples)  # (S,) T_j
    w = trans * -torch.expm1(-tau)
    if eps > 0:
        w = torch.where(trans >= eps, w, torch.zeros_like(w))
    dev = sigmas.device
    opacity = torch.zeros(n_rays, dtype=torch.float64, device=dev).index_add(0, ri, w)
    depth = torch.zeros(n_rays, dtype=torch.float64, device=dev).index_add(0, ri, w * tm)
    rgb = torch.zeros(n_rays, 3, dtype=torch.float64, device=dev).index_add(
        0, ri, w[:, None] * rgbs.to(torch.float64)
    )
    if background is not None:
        rgb = rgb + (1 - opacity)[:, None] * background.to(torch.float64)
    dt = sigmas.dtype
    return RenderOutput(
        rgb=rgb.to(dt), depth=depth.to(dt), opacity=opacity.to(dt), weights=w.to(dt)
    )


# ----------------------------------------------------------------------------- numba


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().contiguous().numpy()


class _CompositeNumba(torch.autograd.Function):
    """Fused forward and closed-form backward (see module docstring), parallel over rays.

    The forward keeps w_j and T_{j+1} in float64 (16 bytes per sample) and the number of
    contributing samples per ray, so the backward needs no transcendental functions.
    """

    @staticmethod
    def forward(ctx, sigmas, rgbs, background, t_starts, t_ends, offsets, eps):
        n = offsets.shape[0] - 1
        s = sigmas.shape[0]
        dt = sigmas.dtype
        bg = _np(background.to(dt).expand(n, 3))
        rgb = np.zeros((n, 3), dtype=_np(sigmas).dtype)
        depth = np.zeros(n, dtype=rgb.dtype)
        opacity = np.zeros(n, dtype=rgb.dtype)
        weights = np.zeros(s, dtype=rgb.dtype)
        w64 = np.zeros(s, dtype=np.float64)
        t_next = np.zeros(s, dtype=np.float64)
        n_used = np.zeros(n, dtype=np.int64)
        _fwd_kernel(
            _np(sigmas),
            _np(rgbs),
            _np(t_starts),
            _np(t_ends),
            _np(offsets),
            bg,
            eps,
            rgb,
            depth,
            opacity,
            weights,
            w64,
            t_next,
            n_used,
        )
        opacity_t = torch.from_numpy(opacity)
        ctx.save_for_backward(rgbs, background, t_starts, t_ends, offsets, opacity_t)
        ctx.kept = (w64, t_next, n_used)  # numpy, not autograd inputs
        return torch.from_numpy(rgb), torch.from_numpy(depth), opacity_t, torch.from_numpy(weights)

    @staticmethod
    def backward(ctx, g_rgb, g_depth, g_opacity, g_weights):
        rgbs, background, t_starts, t_ends, offsets, opacity = ctx.saved_tensors
        w64, t_next, n_used = ctx.kept
        n = offsets.shape[0] - 1
        dt = opacity.dtype
        g_sig = g_col = g_bg = None
        if ctx.needs_input_grad[0] or ctx.needs_input_grad[1]:
            g_sig_np = np.zeros(w64.shape[0], dtype=_np(opacity).dtype)
            g_col_np = np.zeros((w64.shape[0], 3), dtype=g_sig_np.dtype)
            _bwd_kernel(
                _np(rgbs),
                _np(t_starts),
                _np(t_ends),
                _np(offsets),
                _np(background.to(dt).expand(n, 3)),
                w64,
                t_next,
                n_used,
                _np(g_rgb.to(dt)),
                _np(g_depth.to(dt)),
                _np(g_opacity.to(dt)),
                _np(g_weights.to(dt)),
                g_sig_np,
                g_col_np,
            )
            g_sig = torch.from_numpy(g_sig_np) if ctx.needs_input_grad[0] else None
            g_col = torch.from_numpy(g_col_np).to(rgbs.dtype) if ctx.needs_input_grad[1] else None
        if ctx.needs_input_grad[2]:
            g_bg = (1 - opacity)[:, None] * g_rgb  # (R, 3)
            if background.dim() == 1:
                g_bg = g_bg.sum(0)
            g_bg = g_bg.to(background.dtype)
        return g_sig, g_col, g_bg, None, None, None, None


@numba.njit(cache=True, inline="always")
def _alpha_keep(tau):  # pragma: no cover - compiled
    """(alpha, 1 - alpha) = (1 - exp(-tau), exp(-tau)), both to full relative precision with one
    transcendental call: expm1 where alpha is small, exp where exp(-tau) is small."""
    if tau < 0.5:
        em = math.expm1(-tau)
        return -em, 1.0 + em
    keep = math.exp(-tau)
    return 1.0 - keep, keep


@numba.njit(cache=True, parallel=True)
def _fwd_kernel(
    sigmas,
    rgbs,
    ts,
    te,
    offsets,
    bg,
    eps,
    out_rgb,
    out_depth,
    out_opacity,
    out_w,
    w64,
    t_next,
    n_used,
):  # pragma: no cover - compiled
    for r in prange(offsets.shape[0] - 1):
        trans = 1.0
        acc_r = 0.0
        acc_g = 0.0
        acc_b = 0.0
        acc_d = 0.0
        acc_a = 0.0
        used = 0
        for j in range(offsets[r], offsets[r + 1]):
            if trans < eps:
                break  # out_w stays 0 for the rest of the ray
            t0 = np.float64(ts[j])
            t1 = np.float64(te[j])
            alpha, keep = _alpha_keep(np.float64(sigmas[j]) * (t1 - t0))
            w = trans * alpha
            out_w[j] = w
            w64[j] = w
            acc_r += w * rgbs[j, 0]
            acc_g += w * rgbs[j, 1]
            acc_b += w * rgbs[j, 2]
            acc_d += w * ((t0 + t1) * 0.5)
            acc_a += w
            trans *= keep
            t_next[j] = trans
            used += 1
        n_used[r] = used
        rest = 1.0 - acc_a
        out_rgb[r, 0] = acc_r + rest * bg[r, 0]
        out_rgb[r, 1] = acc_g + rest * bg[r, 1]
        out_rgb[r, 2] = acc_b + rest * bg[r, 2]
        out_depth[r] = acc_d
        out_opacity[r] = acc_a


@numba.njit(cache=True, parallel=True)
def _bwd_kernel(
    rgbs,
    ts,
    te,
    offsets,
    bg,
    w64,
    t_next,
    n_used,
    g_rgb,
    g_depth,
    g_opacity,
    g_w,
    out_g_sigma,
    out_g_rgb,
):  # pragma: no cover - compiled
    for r in prange(offsets.shape[0] - 1):
        gr = np.float64(g_rgb[r, 0])
        gg = np.float64(g_rgb[r, 1])
        gb = np.float64(g_rgb[r, 2])
        gd = np.float64(g_depth[r])
        base = np.float64(g_opacity[r]) - gr * bg[r, 0] - gg * bg[r, 1] - gb * bg[r, 2]
        first = offsets[r]
        stop = first + n_used[r]  # samples after early termination get no gradient
        # Pass 1: total = sum_j e_j w_j.
        total = 0.0
        for j in range(first, stop):
            e = (
                g_w[j]
                + base
                + gr * rgbs[j, 0]
                + gg * rgbs[j, 1]
                + gb * rgbs[j, 2]
                + gd * ((np.float64(ts[j]) + np.float64(te[j])) * 0.5)
            )
            total += e * w64[j]
        # Pass 2: dL/dtau_k = e_k T_{k+1} - (total - prefix_k), prefix_k = sum_{j<=k} e_j w_j.
        prefix = 0.0
        for j in range(first, stop):
            t0 = np.float64(ts[j])
            t1 = np.float64(te[j])
            e = (
                g_w[j]
                + base
                + gr * rgbs[j, 0]
                + gg * rgbs[j, 1]
                + gb * rgbs[j, 2]
                + gd * ((t0 + t1) * 0.5)
            )
            w = w64[j]
            prefix += e * w
            out_g_sigma[j] = (e * t_next[j] - (total - prefix)) * (t1 - t0)
            out_g_rgb[j, 0] = w * gr
            out_g_rgb[j, 1] = w * gg
            out_g_rgb[j, 2] = w * gb
