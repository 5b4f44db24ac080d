"""NeuS volume rendering: camera rays, sampling inside the object's box, unbiased weights, importance sampling.

Coordinates are the network's normalised frame (see `Normaliser`): rays are generated from OpenCV intrinsics
and camera-to-turntable poses in metres and mapped into it. Per ray: stratified coarse samples between the
box entry and exit are evaluated without gradients, NeuS's hierarchical up-sampling (the logistic density at
a growing fixed sharpness) adds importance samples near the surface, and the final, differentiable pass
evaluates the importance samples plus every k-th coarse sample as sections that tile the ray. Colour is only
evaluated where a section's weight is not negligible (weights depend on the SDF alone).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from n2d_common.config import check_ranges

if TYPE_CHECKING:
    from n2d_reconstruct.neus.field import NeusNetwork

COLOUR_MIN_WEIGHT = 1e-4
"""Sections with a smaller rendering weight skip the colour network (their contribution is ignored)."""


@dataclass
class RenderSpec:
    """Samples per ray."""

    coarse_samples: int = 32
    """Stratified samples between box entry and exit, evaluated without gradients."""
    importance_samples: int = 32
    """Samples added near the surface by hierarchical up-sampling."""
    up_sample_steps: int = 4
    """Up-sampling rounds (each adds importance_samples / up_sample_steps, at twice the sharpness)."""
    coarse_every: int = 4
    """Every k-th coarse sample also goes into the differentiable pass (free-space supervision)."""
    base_inv_s: float = 64.0
    """Sharpness (1 / normalised units) of the first up-sampling round."""

    def __post_init__(self):
        check_ranges(self, positive=("coarse_samples", "coarse_every", "base_inv_s"),
                     non_negative=("importance_samples", "up_sample_steps"))


@dataclass
class Normaliser:
    """Maps turntable metres to the network frame: x_n = (x - centre) / scale, the box inside [-1, 1]^3."""

    centre: np.ndarray
    scale_m: float
    lo: np.ndarray
    """Box minimum, normalised."""
    hi: np.ndarray
    """Box maximum, normalised."""

    @classmethod
    def from_aabb(cls, aabb: np.ndarray) -> Normaliser:
        aabb = np.asarray(aabb, dtype=np.float64).reshape(2, 3)
        centre, half = aabb.mean(0), (aabb[1] - aabb[0]) / 2
        scale = float(half.max())
        return cls(centre, scale, (aabb[0] - centre) / scale, (aabb[1] - centre) / scale)

    def to_net(self, x: np.ndarray) -> np.ndarray:
        return (np.asarray(x, dtype=np.float64) - self.centre) / self.scale_m


@dataclass
class RayOutput:
    """What rendering a batch of R rays gives."""

    rgb: torch.Tensor
    """R x 3 colour composited on black."""
    acc: torch.Tensor
    """R accumulated opacity."""
    grad: torch.Tensor
    """S x 3 SDF gradients at every differentiable sample (eikonal loss)."""
    depth: torch.Tensor
    """R expected ray distance (normalised units)."""


def camera_rays(K: np.ndarray, T: np.ndarray, u: torch.Tensor, v: torch.Tensor, norm: Normaliser,
                device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """Origins and unit directions (normalised frame) of pixels (u, v) (OpenCV, centres at integers)."""
    T = torch.as_tensor(T, dtype=torch.float32, device=device)
    fx, fy, cx, cy = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    d = torch.stack([(u - cx) / fx, (v - cy) / fy, torch.ones_like(u)], -1)
    if T.ndim == 2:
        d = d @ T[:3, :3].T
        o = T[:3, 3].expand_as(d)
    else:  # one pose per ray
        d = torch.einsum("nij,nj->ni", T[:, :3, :3], d)
        o = T[:, :3, 3]
    centre = torch.as_tensor(norm.centre, dtype=torch.float32, device=device)
    return (o - centre) / norm.scale_m, d / d.norm(dim=-1, keepdim=True)


def box_intersect(o: torch.Tensor, d: torch.Tensor, lo: np.ndarray, hi: np.ndarray):
    """Ray-box (slab) entry and exit distances, and which rays hit the box in front of the camera."""
    lo = torch.as_tensor(lo, dtype=o.dtype, device=o.device)
    hi = torch.as_tensor(hi, dtype=o.dtype, device=o.device)
    inv = 1.0 / torch.where(d.abs() < 1e-9, torch.full_like(d, 1e-9), d)
    t0, t1 = (lo - o) * inv, (hi - o) * inv
    near = torch.minimum(t0, t1).amax(-1).clamp_min(0.0)
    far = torch.maximum(t0, t1).amin(-1)
    return near, far, far > near + 1e-6


def sample_pdf(bins: torch.Tensor, weights: torch.Tensor, n: int, jitter: bool) -> torch.Tensor:
    """n distances per ray drawn from the piecewise-constant density `weights` over the intervals `bins`."""
    weights = weights + 1e-5
    cdf = torch.cumsum(weights / weights.sum(-1, keepdim=True), -1)
    cdf = torch.cat([torch.zeros_like(cdf[:, :1]), cdf], -1)
    u = (torch.arange(n, device=bins.device, dtype=bins.dtype) + 0.5) / n
    u = u.expand(bins.shape[0], n)
    if jitter:
        u = u + (torch.rand_like(u) - 0.5) / n
    u = u.contiguous()
    inds = torch.searchsorted(cdf, u, right=True)
    below = (inds - 1).clamp_min(0)
    above = inds.clamp_max(cdf.shape[-1] - 1)
    cdf0, cdf1 = cdf.gather(1, below), cdf.gather(1, above)
    bin0, bin1 = bins.gather(1, below), bins.gather(1, above)
    denom = torch.where(cdf1 - cdf0 < 1e-5, torch.ones_like(cdf0), cdf1 - cdf0)
    return bin0 + (u - cdf0) / denom * (bin1 - bin0)


def _coarse_weights(z: torch.Tensor, sdf: torch.Tensor, inv_s: float) -> torch.Tensor:
    """NeuS's section weights from SDF values at sorted samples, slopes estimated from neighbours."""
    prev_sdf, next_sdf = sdf[:, :-1], sdf[:, 1:]
    dist = z[:, 1:] - z[:, :-1]
    mid_sdf = (prev_sdf + next_sdf) * 0.5
    cos = (next_sdf - prev_sdf) / (dist + 1e-5)
    cos = torch.minimum(torch.cat([torch.zeros_like(cos[:, :1]), cos[:, :-1]], -1), cos).clamp(-1e3, 0.0)
    prev_cdf = torch.sigmoid((mid_sdf - cos * dist * 0.5) * inv_s)
    next_cdf = torch.sigmoid((mid_sdf + cos * dist * 0.5) * inv_s)
    alpha = (prev_cdf - next_cdf + 1e-5) / (prev_cdf + 1e-5)
    return alpha * _transmittance(alpha)


def _transmittance(alpha: torch.Tensor) -> torch.Tensor:
    """Exclusive cumulative product of (1 - alpha) along each ray."""
    trans = torch.cumprod(1.0 - alpha + 1e-7, -1)
    return torch.cat([torch.ones_like(trans[:, :1]), trans[:, :-1]], -1)


def _points(o: torch.Tensor, d: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
    return (o[:, None, :] + d[:, None, :] * z[..., None]).reshape(-1, 3)


def sample_rays(net: NeusNetwork, o: torch.Tensor, d: torch.Tensor, near: torch.Tensor, far: torch.Tensor,
                spec: RenderSpec, jitter: bool) -> torch.Tensor:
    """Sorted distances of the differentiable pass (R x M): kept coarse samples plus importance samples."""
    n = spec.coarse_samples
    steps = torch.arange(n, device=o.device, dtype=o.dtype)
    offset = torch.rand(o.shape[0], n, device=o.device) if jitter else torch.full((o.shape[0], n), 0.5,
                                                                                     device=o.device)
    z = near[:, None] + (far - near)[:, None] * (steps + offset) / n
    keep = [z[:, :: max(spec.coarse_every, 1)]] if spec.coarse_every > 0 else [z[:, :1]]
    rounds = max(spec.up_sample_steps, 1) if spec.importance_samples > 0 else 0
    with torch.no_grad():
        sdf = net.sdf(_points(o, d, z)).view_as(z)
        for i in range(rounds):
            count = spec.importance_samples // rounds + (i < spec.importance_samples % rounds)
            weights = _coarse_weights(z, sdf, spec.base_inv_s * 2**i)
            new = sample_pdf(z, weights, count, jitter)
            keep.append(new)
            if i + 1 < rounds:
                new_sdf = net.sdf(_points(o, d, new)).view_as(new)
                z, order = torch.sort(torch.cat([z, new], -1), -1)
                sdf = torch.cat([sdf, new_sdf], -1).gather(1, order)
    return torch.sort(torch.cat(keep, -1), -1).values


def _section_weights(net: NeusNetwork, o, d, near, far, spec: RenderSpec, jitter: bool, cos_anneal: float):
    """The differentiable pass: geometry at section midpoints and NeuS's unbiased weights (R x M)."""
    z = sample_rays(net, o, d, near, far, spec, jitter)
    rays, m = z.shape
    dists = torch.diff(torch.cat([z, far[:, None]], -1), dim=-1).clamp_min(1e-6)
    mid = z + dists * 0.5
    dirs = d[:, None, :].expand(rays, m, 3).reshape(-1, 3)
    geo = net.geometry(_points(o, d, mid), gradient=True)
    true_cos = (dirs * geo.grad).sum(-1)
    # NeuS cos annealing: early on, back-facing sections also get a slope, so gradients reach everywhere
    iter_cos = -(torch.relu(-true_cos * 0.5 + 0.5) * (1.0 - cos_anneal) + torch.relu(-true_cos) * cos_anneal)
    half = iter_cos * dists.reshape(-1) * 0.5
    inv_s = net.inv_s()
    prev_cdf = torch.sigmoid((geo.sdf - half) * inv_s)
    next_cdf = torch.sigmoid((geo.sdf + half) * inv_s)
    alpha = ((prev_cdf - next_cdf + 1e-5) / (prev_cdf + 1e-5)).clamp(0.0, 1.0).view(rays, m)
    return geo, alpha * _transmittance(alpha), mid, dirs


def render_rays(net: NeusNetwork, o: torch.Tensor, d: torch.Tensor, near: torch.Tensor, far: torch.Tensor,
                spec: RenderSpec, *, jitter: bool, cos_anneal: float = 1.0) -> RayOutput:
    """Volume-render R rays that hit the box (NeuS unbiased weights); differentiable w.r.t. the networks."""
    geo, weights, mid, dirs = _section_weights(net, o, d, near, far, spec, jitter, cos_anneal)
    rays, m = weights.shape
    flat_w = weights.reshape(-1)
    live = torch.nonzero(flat_w.detach() > COLOUR_MIN_WEIGHT).squeeze(1)
    rgb = torch.zeros(rays, 3, device=o.device, dtype=o.dtype)
    if live.numel():
        sub = type(geo)(geo.sdf[live], None, geo.geo[live], geo.enc[live], geo.x[live])
        normals = torch.nn.functional.normalize(geo.grad[live], dim=-1)
        colour = net.colour(sub, normals, dirs[live])
        rgb = rgb.index_add(0, torch.div(live, m, rounding_mode="floor"), colour * flat_w[live, None])
    return RayOutput(rgb, weights.sum(-1), geo.grad, (weights * mid).sum(-1))


@torch.no_grad()
def surface_samples(net: NeusNetwork, o: torch.Tensor, d: torch.Tensor, near: torch.Tensor, far: torch.Tensor,
                    spec: RenderSpec, k: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The k heaviest sections of each ray as `render_rays` places them: points, unit normals (R x k x 3)
    and weights (R x k, scaled to the ray's whole opacity). Colour training on these alone reproduces the
    rendering of a frozen geometry (exactly when the rest of the weight is negligible: a sharp surface)."""
    geo, weights, _, _ = _section_weights(net, o, d, near, far, spec, False, 1.0)
    rays, m = weights.shape
    w, idx = weights.topk(min(k, m), dim=-1)
    w = w * (weights.sum(-1, keepdim=True) / w.sum(-1, keepdim=True).clamp_min(1e-6))
    rows = (idx + torch.arange(rays, device=o.device)[:, None] * m).reshape(-1)
    normals = torch.nn.functional.normalize(geo.grad[rows], dim=-1)
    return geo.x[rows].view(rays, -1, 3), normals.view(rays, -1, 3), w


def pixel_grid(width: int, height: int, pixel_mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(v, u) integer coordinates of the pixels to render (all, or those of the mask)."""
    if pixel_mask is None:
        v, u = np.mgrid[0:height, 0:width]
        return v.reshape(-1), u.reshape(-1)
    mask = np.asarray(pixel_mask, dtype=bool)
    if mask.shape != (height, width):
        raise ValueError(f"pixel_mask is {mask.shape}, the image {(height, width)}")
    return np.nonzero(mask)
