"""The NeuS networks: hash-grid SDF with an analytic gradient, colour network, learned inverse variance.

All coordinates here are normalised: the trainer maps the object's box to [-1, 1]^3 (centre and one scale),
so one set of hyper-parameters serves any object size. The SDF network is a small MLP on (point, hash
encoding); its gradient d sdf / d point is computed in closed form (the MLP's input gradient by a manual
backward pass, chained with the encoding's Jacobian), so normals and the eikonal loss are ordinary
differentiable tensors and training never needs a double backward through the hash table.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn import functional

from n2d_common.config import check_ranges
from n2d_common.torch_utils import atomic_torch_save, load_checkpoint, resolve_device
from n2d_reconstruct.neus.encoding import HashGrid
from n2d_reconstruct.neus.renderer import Normaliser, RenderSpec, box_intersect, camera_rays, pixel_grid, render_rays

SOFTPLUS_BETA = 100.0
"""Sharpness of the SDF network's softplus activations (IDR / NeuS)."""


@dataclass
class FieldSpec:
    """The network shape: every number that must match between a checkpoint and the code loading it."""

    levels: int = 16
    """Hash grid levels."""
    features: int = 2
    """Features per grid vertex."""
    log2_table: int = 19
    """log2 of the hash table rows per level."""
    base_res: int = 16
    """Coarsest grid: cells per axis over the normalised cube (the box's longest side)."""
    max_res: int = 1024
    """Finest grid: cells per axis over the normalised cube."""
    sdf_hidden: int = 64
    """Width of the SDF MLP."""
    sdf_layers: int = 1
    """Hidden layers of the SDF MLP."""
    geo_features: int = 15
    """Geometry features the SDF MLP passes to the colour MLP."""
    colour_hidden: int = 64
    """Width of the colour MLP."""
    colour_layers: int = 2
    """Hidden layers of the colour MLP."""
    colour_levels: int = 0
    """Levels of a separate appearance hash grid (0: the colour MLP reads the geometry grid)."""
    colour_features: int = 2
    """Features per vertex of the appearance grid."""
    colour_log2_table: int = 19
    """log2 of the appearance grid's table rows per level."""
    colour_base_res: int = 16
    """Coarsest appearance grid (cells per axis over the normalised cube)."""
    colour_max_res: int = 2048
    """Finest appearance grid (cells per axis over the normalised cube)."""
    init_radius: float = 0.5
    """Radius of the initial SDF sphere (normalised: the box's largest half-extent is 1)."""
    init_variance: float = 0.3
    """Initial NeuS variance parameter: inverse sharpness s = exp(10 * variance)."""

    def __post_init__(self):
        check_ranges(self, positive=("levels", "features", "base_res", "sdf_hidden", "colour_hidden",
                                     "colour_features", "colour_base_res", "init_radius"),
                     non_negative=("sdf_layers", "geo_features", "colour_layers", "colour_levels"))
        if not (1 <= self.log2_table <= 30 and 1 <= self.colour_log2_table <= 30):
            raise ValueError("log2_table and colour_log2_table must be in [1, 30] (2^k hash table rows per level)")
        if self.max_res < self.base_res or self.colour_max_res < self.colour_base_res:
            raise ValueError("max_res must be >= base_res and colour_max_res >= colour_base_res")
        if not self.init_radius < 1:
            raise ValueError(f"init_radius must be < 1 (the box's largest half-extent), got {self.init_radius!r}")
        if not math.isfinite(self.init_variance):
            raise ValueError(f"init_variance must be a number, got {self.init_variance!r}")


@dataclass
class FieldOutput:
    """What the networks say about N points (normalised units)."""

    sdf: torch.Tensor
    """N signed distances."""
    grad: torch.Tensor | None
    """N x 3 SDF gradients (None when not asked for)."""
    geo: torch.Tensor
    """N x geo_features geometry features for the colour network."""
    enc: torch.Tensor
    """N x levels*features hash encoding (level-masked)."""
    x: torch.Tensor
    """N x 3 the points."""


def sh_encode(d: torch.Tensor) -> torch.Tensor:
    """Real spherical harmonics of unit directions up to degree 3: N x 16."""
    x, y, z = d.unbind(-1)
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    return torch.stack([
        torch.full_like(x, 0.28209479177387814), -0.48860251190291987 * y, 0.48860251190291987 * z,
        -0.48860251190291987 * x, 1.0925484305920792 * xy, -1.0925484305920792 * yz,
        0.94617469575755997 * zz - 0.31539156525251999, -1.0925484305920792 * xz,
        0.54627421529603959 * (xx - yy), 0.59004358992664352 * y * (-3.0 * xx + yy),
        2.8906114426405538 * xy * z, 0.45704579946446572 * y * (1.0 - 5.0 * zz),
        0.3731763325901154 * z * (5.0 * zz - 3.0), 0.45704579946446572 * x * (1.0 - 5.0 * zz),
        1.4453057213202769 * z * (xx - yy), 0.59004358992664352 * x * (-xx + 3.0 * yy)], -1)


class NeusNetwork(nn.Module):
    """SDF + colour networks over one hash grid, and the learned variance of NeuS."""

    def __init__(self, spec: FieldSpec):
        super().__init__()
        self.spec = spec
        self.grid = HashGrid(spec.levels, spec.features, spec.log2_table, spec.base_res, spec.max_res)
        dims = [3 + self.grid.out_dim] + [spec.sdf_hidden] * spec.sdf_layers + [1 + spec.geo_features]
        self.sdf_layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:]))
        self.colour_grid = None
        if spec.colour_levels > 0:  # appearance in a grid of its own (geometry and texture do not compete)
            self.colour_grid = HashGrid(spec.colour_levels, spec.colour_features, spec.colour_log2_table,
                                        spec.colour_base_res, spec.colour_max_res)
        colour_in = spec.geo_features + (self.colour_grid or self.grid).out_dim + 3 + 16
        dims = [colour_in] + [spec.colour_hidden] * spec.colour_layers + [3]
        self.colour_layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:]))
        self.variance = nn.Parameter(torch.tensor(float(spec.init_variance)))
        self.register_buffer("level_mask", torch.ones(spec.levels))
        self._sphere_init(spec.init_radius)

    def _sphere_init(self, radius: float) -> None:
        """Geometric initialisation (IDR): the SDF starts as a sphere of `radius`, encoding inputs at zero."""
        layers = self.sdf_layers
        for i, layer in enumerate(layers):
            fan_out = layer.out_features
            if i == len(layers) - 1:
                nn.init.normal_(layer.weight, math.sqrt(math.pi) / math.sqrt(layer.in_features), 1e-4)
                nn.init.constant_(layer.bias, -radius)
            else:
                nn.init.normal_(layer.weight, 0.0, math.sqrt(2.0) / math.sqrt(fan_out))
                nn.init.constant_(layer.bias, 0.0)
                if i == 0:
                    nn.init.constant_(layer.weight[:, 3:], 0.0)

    def inv_s(self) -> torch.Tensor:
        """The inverse standard deviation s of NeuS's logistic density (normalised units)."""
        return torch.exp(self.variance * 10.0).clamp(1e-6, 1e6)

    def geometry(self, x: torch.Tensor, gradient: bool = False) -> FieldOutput:
        """SDF (and its gradient, analytic) of N x 3 normalised points; everything differentiable."""
        enc, jac = self.grid((x + 1.0) * 0.5, jacobian=gradient, level_mask=self.level_mask)
        h = torch.cat([x, enc], -1)
        pre = []
        for layer in self.sdf_layers[:-1]:
            z = layer(h)
            pre.append(z)
            h = functional.softplus(z, beta=SOFTPLUS_BETA)
        out = self.sdf_layers[-1](h)
        grad = None
        if gradient:  # manual backward of out[:, 0] through the MLP, then through the encoding
            v = self.sdf_layers[-1].weight[0][None, :]
            for layer, z in zip(reversed(self.sdf_layers[:-1]), reversed(pre)):
                v = (v * torch.sigmoid(SOFTPLUS_BETA * z)) @ layer.weight
            grad = v[:, :3] + HashGrid.contract(jac, v[:, 3:]) * 0.5
        return FieldOutput(out[:, 0], grad, out[:, 1:], enc, x)

    def sdf(self, x: torch.Tensor) -> torch.Tensor:
        """SDF only (normalised units), for sampling and meshing."""
        return self.geometry(x).sdf

    def colour(self, geo: FieldOutput, normals: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
        """sRGB in [0, 1] seen along unit `dirs` at points with geometry `geo` and unit `normals`."""
        enc = geo.enc if self.colour_grid is None else self.colour_grid((geo.x + 1.0) * 0.5)[0]
        h = torch.cat([geo.geo, enc, normals, sh_encode(dirs)], -1)
        for layer in self.colour_layers[:-1]:
            h = functional.relu(layer(h))
        return torch.sigmoid(self.colour_layers[-1](h))

    def set_level_mask(self, active: float) -> None:
        """Use the first `active` levels (fractional: the next level fades in linearly)."""
        levels = torch.arange(self.spec.levels, dtype=torch.float32, device=self.level_mask.device)
        self.level_mask.copy_((active - levels).clamp(0.0, 1.0))


class NeusField:
    """A trained NeuS field in the turntable frame (metres): SDF, albedo and volume rendering on numpy arrays.

    The field is only defined inside its box (`aabb`): `sdf` is the intersection of the network's shape with
    the box, so the zero level set is closed where the box cuts it (e.g. at the plate, z = aabb z-min).
    """

    def __init__(self, net: NeusNetwork, aabb: np.ndarray, render_spec: RenderSpec, device: str = "auto"):
        self.device = resolve_device(device)
        self.net = net.to(self.device).eval()
        self.aabb = np.asarray(aabb, dtype=np.float64).reshape(2, 3)
        self.norm = Normaliser.from_aabb(self.aabb)
        self.render_spec = render_spec
        self.chunk_points = 1 << 16
        """Points per network call (memory bound)."""
        self.chunk_rays = 2048
        """Rays per rendering call."""

    def _net_points(self, points: np.ndarray) -> torch.Tensor:
        return self._tensor(self.norm.to_net(points))

    def _tensor(self, array: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(array, dtype=torch.float32, device=self.device)

    @torch.no_grad()
    def sdf(self, points: np.ndarray) -> np.ndarray:
        """Signed distance (metres, negative inside) of N x 3 turntable points, batched, no gradients."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        out = np.empty(len(points), dtype=np.float64)
        for s in range(0, len(points), self.chunk_points):
            x = self._net_points(points[s:s + self.chunk_points])
            out[s:s + len(x)] = self.net.sdf(x.clamp(-1.0, 1.0)).double().cpu().numpy() * self.norm.scale_m
        return np.maximum(out, _box_sdf(points, self.aabb))

    @torch.no_grad()
    def albedo(self, points: np.ndarray, normals: np.ndarray, eyes: np.ndarray | None = None, *, k: int = 4,
               sharpness: float = 6.0, min_cos: float = 0.15) -> np.ndarray:
        """Colour (N x 3 sRGB in [0, 1]) of surface points with outward `normals`.

        Without `eyes` each point is seen along its normal. With `eyes` (M x 3 camera centres, turntable frame,
        e.g. the training cameras) it is the colour seen from the `k` most frontal of them, blended with
        weights cos^sharpness (cameras under `min_cos` left out; none left: along the normal), so the colour
        network is only asked about directions it was trained on (from a ring of views, a side's normal
        direction is not one of them). Each colour is the field's where the viewing ray through the point meets
        the field's own surface (Newton steps along the ray), with the field's normal there: what that camera's
        pixel saw. A mesh smoothed or denoised after meshing lies a little off that surface.
        """
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        out = np.empty((len(points), 3), dtype=np.float32)
        step = max(1, self.chunk_points // (k if eyes is not None else 1))
        for s in range(0, len(points), step):
            p, n = points[s:s + step], normals[s:s + step]
            dirs, weights = -n[:, None], np.ones((len(p), 1))
            if eyes is not None:
                dirs, weights = frontal_views(p, n, np.asarray(eyes, dtype=np.float64), k, sharpness, min_cos)
            m = dirs.shape[1]
            rays = self._tensor(dirs.reshape(-1, 3))
            geo = self._along_ray(self._net_points(p).clamp(-1.0, 1.0).repeat_interleave(m, 0), rays)
            colour = self.net.colour(geo, functional.normalize(geo.grad, dim=-1), rays)
            colour = colour.view(len(p), m, 3).cpu().numpy()
            out[s:s + len(p)] = (colour * weights[..., None]).sum(1) / weights.sum(1, keepdims=True)
        return out

    def _along_ray(self, x: torch.Tensor, dirs: torch.Tensor, steps: int = 3, max_step: float = 0.05,
                   tolerance: float = 0.005) -> FieldOutput:
        """Geometry (with gradient) where rays along unit `dirs` through normalised points `x` meet the zero
        level set: Newton steps on sdf(x + t d), each at most `max_step` (normalised units). A ray whose steps
        end further than `tolerance` from the level set (a grazing ray that stepped off the surface, where the
        colour network's answer is meaningless) keeps its starting point."""
        start = x
        for _ in range(steps):
            geo = self.net.geometry(x, gradient=True)
            slope = (geo.grad * dirs).sum(-1)
            slope = torch.minimum(slope, -0.1 * geo.grad.norm(dim=-1).clamp_min(1e-6))  # the ray enters the surface
            t = (-geo.sdf / slope).clamp(-max_step, max_step)
            x = (x + t[:, None] * dirs).clamp(-1.0, 1.0)
        off = self.net.geometry(x).sdf.abs() > tolerance
        return self.net.geometry(torch.where(off[:, None], start, x), gradient=True)

    @torch.no_grad()
    def render(self, K: np.ndarray, T_turntable_cam: np.ndarray, width: int, height: int,
               pixel_mask: np.ndarray | None = None) -> np.ndarray:
        """Volume-rendered H x W x 3 sRGB image in [0, 1] on black; pixels outside `pixel_mask` are 0."""
        image = np.zeros((height, width, 3), dtype=np.float32)
        v, u = pixel_grid(width, height, pixel_mask)
        for s in range(0, len(u), self.chunk_rays):
            uu = torch.as_tensor(u[s:s + self.chunk_rays], dtype=torch.float32, device=self.device)
            vv = torch.as_tensor(v[s:s + self.chunk_rays], dtype=torch.float32, device=self.device)
            o, d = camera_rays(K, T_turntable_cam, uu, vv, self.norm, self.device)
            near, far, hit = box_intersect(o, d, self.norm.lo, self.norm.hi)
            if not hit.any():
                continue
            out = render_rays(self.net, o[hit], d[hit], near[hit], far[hit], self.render_spec, jitter=False)
            rows = np.nonzero(hit.cpu().numpy())[0] + s
            image[v[rows], u[rows]] = out.rgb.clamp(0.0, 1.0).cpu().numpy()
        return image

    def state(self) -> dict:
        """What `save` writes (the trainer adds its own entries to checkpoints)."""
        return {"field_spec": asdict(self.net.spec), "render_spec": asdict(self.render_spec),
                "aabb": self.aabb.tolist(), "network": self.net.state_dict()}

    def save(self, path: str | Path) -> None:
        """Write the field to `path` (torch file), atomically."""
        atomic_torch_save(self.state(), path)

    @classmethod
    def load(cls, path: str | Path, device: str = "auto") -> NeusField:
        """Read a field written by `save` or a training checkpoint."""
        state = load_checkpoint(path)
        net = NeusNetwork(FieldSpec(**state["field_spec"]))
        net.load_state_dict(state["network"])
        return cls(net, np.asarray(state["aabb"]), RenderSpec(**state["render_spec"]), device)


def frontal_views(points: np.ndarray, normals: np.ndarray, eyes: np.ndarray, k: int, sharpness: float,
                   min_cos: float) -> tuple[np.ndarray, np.ndarray]:
    """N x k unit viewing directions (camera to point) of each point's k most frontal `eyes`, and their weights
    cos^sharpness (0 for cameras under min_cos; a point with none is seen along its normal, weight 1)."""
    to_eye = eyes[None] - points[:, None]                                        # N x M x 3
    dist = np.linalg.norm(to_eye, axis=-1)
    cos = np.einsum("nmc,nc->nm", to_eye, normals) / dist
    best = np.argsort(-cos, axis=1)[:, :k]
    cos_k = np.take_along_axis(cos, best, 1)
    dirs = -np.take_along_axis(to_eye / dist[..., None], best[..., None], 1)
    weights = np.where(cos_k > min_cos, np.maximum(cos_k, 0.0) ** sharpness, 0.0)
    none = weights.sum(1) == 0
    dirs[none], weights[none] = -normals[none, None], np.eye(1, best.shape[1])
    return dirs, weights


def _box_sdf(points: np.ndarray, aabb: np.ndarray) -> np.ndarray:
    """Signed distance to the box `aabb` (negative inside)."""
    centre, half = aabb.mean(0), (aabb[1] - aabb[0]) / 2
    q = np.abs(points - centre) - half
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(-1), 0.0)
