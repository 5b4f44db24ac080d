"""NeuS training: configuration and presets, ray batches from masked views, losses, checkpoints, resume.

Losses per batch: colour (mean squared error, sRGB [0, 1], composited on black) on rays whose pixel is in
the object mask only; mask (binary cross-entropy between accumulated opacity and the mask) on all rays, so
background rays clear the free space; eikonal on every differentiable sample; surface smoothness (UNISURF,
capped at edges; on in the cpu and gpu presets) at the mask rays' surface points. Rays come mostly from mask
pixels, the rest from background pixels inside each view's dilated mask bounding box whose rays cross the
object's box. With `init_sdf` the SDF network is first fitted to that shape (truncated L1 + eikonal).
"""

from __future__ import annotations

import hashlib
import math
import threading
from collections.abc import Callable
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional

from n2d_common.errors import Cancelled, N2DError
from n2d_common.progress import Eta, Progress, ProgressFn, no_progress
from n2d_common.torch_utils import atomic_torch_save, load_checkpoint, resolve_device
from n2d_reconstruct.data import Views
from n2d_reconstruct.neus.field import FieldSpec, NeusField, NeusNetwork
from n2d_reconstruct.neus.renderer import (
    Normaliser,
    RenderSpec,
    box_intersect,
    camera_rays,
    render_rays,
    surface_samples,
)

CHECKPOINT = "neus.pt"
"""Checkpoint file name inside the work directory."""


@dataclass
class NeusConfig:
    """Every tunable of NeuS training. Distances are in the network frame unless named _m (metres)."""

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
    rays: int = 1024
    """Rays per training batch."""
    background_fraction: float = 0.2
    """Share of each batch's rays drawn from background pixels (mask loss only)."""
    bbox_margin: float = 0.25
    """Background rays come from each view's mask bounding box grown by this fraction of its size."""
    coarse_samples: int = 32
    """Stratified samples per ray evaluated without gradients."""
    importance_samples: int = 32
    """Importance samples per ray near the surface (differentiable)."""
    up_sample_steps: int = 4
    """Rounds of hierarchical up-sampling."""
    coarse_every: int = 4
    """Every k-th coarse sample joins the differentiable pass."""
    steps: int = 5000
    """Training steps (batches)."""
    lr: float = 1e-2
    """Peak learning rate (Adam) of the hash grid and MLPs."""
    lr_variance: float = 1e-3
    """Learning rate of the variance parameter."""
    lr_final_factor: float = 0.05
    """The learning rate decays by cosine to lr * this at the last step."""
    warmup_steps: int = 200
    """Linear learning-rate warm-up steps."""
    cos_anneal_steps: int = 1000
    """Steps over which NeuS's cosine annealing ratio goes from 0 to 1."""
    eikonal_weight: float = 0.1
    """Weight of the eikonal loss (|grad sdf| - 1)^2."""
    mask_weight: float = 0.1
    """Weight of the mask (opacity) binary cross-entropy."""
    smooth_weight: float = 0.0
    """Weight of the surface smoothness loss (UNISURF): the mean |n(x) - n(x + e)| of unit normals at each mask
    ray's surface point x and a point e ~ N(0, smooth_radius_m) away. Where the photos are uniform nothing else
    places the surface, and the hash grid keeps the lumps of its initial shape."""
    smooth_radius_m: float = 0.003
    """Standard deviation of the smoothness loss's offsets, metres."""
    smooth_edge_deg: float = 0.0
    """Pairs of normals further apart than this angle count as an edge and add a constant (no gradient), so the
    loss flattens small bumps without rounding the object's edges (0: every pair counts in full)."""
    level_start: int = 0
    """Coarse-to-fine: active hash levels at step 0 (0 = all levels from the start)."""
    level_every_steps: int = 0
    """Coarse-to-fine: steps until the next level is fully active."""
    texture_steps: int = 0
    """Appearance steps after the NeuS steps: geometry frozen, colour fitted on cached surface samples."""
    texture_rays: int = 8192
    """Rays per appearance step."""
    texture_samples: int = 4
    """Heaviest sections per ray cached for the appearance stage."""
    texture_lr: float = 1e-2
    """Peak learning rate of the appearance stage (cosine decay to lr_final_factor of it)."""
    pretrain_steps: int = 300
    """Steps fitting the SDF to init_sdf (when given)."""
    pretrain_points: int = 8192
    """Points per pretraining step."""
    pretrain_truncation: float = 0.1
    """Pretraining compares SDFs clamped to +- this (normalised units)."""
    device: str = "auto"
    """"auto" (CUDA when available), "cpu" or "cuda"."""
    seed: int = 0
    """Seed of weights, ray batches and samples."""
    checkpoint_every: int = 500
    """Steps between checkpoints (also written on cancel and at the end)."""
    progress_every: int = 10
    """Steps between progress reports."""

    def __post_init__(self):
        for names, low, ok in ((_POSITIVE, "> 0", lambda v: v > 0), (_NON_NEGATIVE, ">= 0", lambda v: v >= 0)):
            for name in names:
                value = getattr(self, name)
                if not (ok(value) and math.isfinite(value)):
                    raise ValueError(f"{name} must be a finite number {low}, got {value!r}")
        if not (1 <= self.log2_table <= 30 and 1 <= self.colour_log2_table <= 30):
            raise ValueError("log2_table and colour_log2_table must be in [1, 30] (2^k hash table rows per level)")
        if self.max_res < self.base_res or self.colour_max_res < self.colour_base_res:
            raise ValueError("max_res must be >= base_res and colour_max_res >= colour_base_res")
        if not self.init_radius < 1:
            raise ValueError(f"init_radius must be < 1 (the box's largest half-extent), got {self.init_radius!r}")
        if not (0 <= self.background_fraction < 1 and 0 <= self.lr_final_factor <= 1):
            raise ValueError("background_fraction must be in [0, 1) and lr_final_factor in [0, 1]")
        if not self.smooth_edge_deg <= 180:
            raise ValueError(f"smooth_edge_deg must be in [0, 180] degrees, got {self.smooth_edge_deg!r}")
        if not math.isfinite(self.init_variance):
            raise ValueError(f"init_variance must be a number, got {self.init_variance!r}")
        try:
            resolve_device(self.device)
        except RuntimeError as exc:
            raise ValueError(f"device {self.device!r}: {exc}; use \"auto\", \"cpu\" or \"cuda\"") from None

    @classmethod
    def preset(cls, name: str) -> NeusConfig:
        """"tiny" (tests, seconds on CPU), "cpu" (2 cores, tens of minutes) or "gpu" (the paper's scale)."""
        if name not in PRESETS:
            raise N2DError(f"unknown NeuS preset {name!r}", f"use one of {', '.join(PRESETS)}")
        return cls(**PRESETS[name])

    def field_spec(self) -> FieldSpec:
        return FieldSpec(**{f.name: getattr(self, f.name) for f in fields(FieldSpec)})

    def render_spec(self) -> RenderSpec:
        return RenderSpec(**{f.name: getattr(self, f.name) for f in fields(RenderSpec) if hasattr(self, f.name)})


PRESETS: dict[str, dict] = {
    "tiny": dict(levels=8, log2_table=14, base_res=8, max_res=128, sdf_hidden=32, geo_features=7,
                 colour_hidden=32, colour_layers=1, rays=256, coarse_samples=16, importance_samples=16,
                 up_sample_steps=2, coarse_every=4, steps=300, warmup_steps=20, cos_anneal_steps=100,
                 lr_variance=3e-3, pretrain_steps=100, pretrain_points=2048, checkpoint_every=100),
    "cpu": dict(levels=16, log2_table=18, max_res=1024, rays=1024, coarse_samples=32, importance_samples=32,
                up_sample_steps=4, coarse_every=4, steps=6000, warmup_steps=200, cos_anneal_steps=1000,
                pretrain_steps=300, checkpoint_every=500, texture_steps=1500, smooth_weight=0.01, smooth_edge_deg=30.0),
    "gpu": dict(levels=16, log2_table=19, max_res=2048, rays=4096, coarse_samples=64, importance_samples=64,
                up_sample_steps=4, coarse_every=1, steps=20000, warmup_steps=500, cos_anneal_steps=5000,
                pretrain_steps=1000, pretrain_points=65536, checkpoint_every=2000, smooth_weight=0.01,
                smooth_edge_deg=30.0),
}
"""Overrides of the defaults per preset."""

_POSITIVE = ("levels", "features", "base_res", "sdf_hidden", "colour_hidden", "colour_features", "colour_base_res",
             "init_radius", "rays", "coarse_samples", "coarse_every", "lr", "smooth_radius_m", "texture_rays",
             "texture_samples", "texture_lr", "pretrain_points", "pretrain_truncation", "checkpoint_every",
             "progress_every")
_NON_NEGATIVE = ("sdf_layers", "geo_features", "colour_layers", "colour_levels", "bbox_margin", "importance_samples",
                 "up_sample_steps", "steps", "lr_variance", "warmup_steps", "cos_anneal_steps", "eikonal_weight",
                 "mask_weight", "smooth_weight", "smooth_edge_deg", "level_start", "level_every_steps",
                 "texture_steps", "pretrain_steps")
"""NeusConfig's range checks."""

_NOT_IDENTITY = ("device", "checkpoint_every", "progress_every")
"""Config fields that do not change the result: a checkpoint written with other values still resumes."""


class RaySampler:
    """Random training rays: pixel colours, mask labels, origins and directions (normalised frame)."""

    def __init__(self, views: Views, norm: Normaliser, cfg: NeusConfig, device: torch.device):
        self.norm, self.cfg, self.device = norm, cfg, device
        self.K = np.asarray(views.K, dtype=np.float64)
        self.h, self.w = views.height, views.width
        self.rgb = torch.as_tensor(views.rgb.reshape(-1, 3), device=device)
        self.poses = torch.as_tensor(views.T_turntable_cam, dtype=torch.float32, device=device)
        fg, bg = [], []
        for i, mask in enumerate(views.masks):
            ys, xs = np.nonzero(mask)
            if len(ys) == 0:
                continue
            grow_y, grow_x = cfg.bbox_margin * (np.ptp(ys) + 1), cfg.bbox_margin * (np.ptp(xs) + 1)
            box = np.zeros_like(mask)
            box[max(0, int(ys.min() - grow_y)):int(ys.max() + grow_y) + 1,
                max(0, int(xs.min() - grow_x)):int(xs.max() + grow_x) + 1] = True
            base = i * self.h * self.w
            fg.append(self._hitting(i, np.flatnonzero(mask)) + base)
            bg.append(self._hitting(i, np.flatnonzero(box & ~mask)) + base)
        self.fg = torch.as_tensor(np.concatenate(fg), device=device)
        self.bg = torch.as_tensor(np.concatenate(bg), device=device)
        if len(self.fg) == 0:
            raise N2DError("no mask pixel of the training views sees the object's box",
                           "check the masks and that the box (aabb) is in the turntable frame, metres")

    def _hitting(self, view: int, pixels: np.ndarray) -> np.ndarray:
        """The pixels (flat indices in one view) whose rays cross the box."""
        u = torch.as_tensor(pixels % self.w, dtype=torch.float32, device=self.device)
        v = torch.as_tensor(pixels // self.w, dtype=torch.float32, device=self.device)
        o, d = camera_rays(self.K, self.poses[view], u, v, self.norm, self.device)
        return pixels[box_intersect(o, d, self.norm.lo, self.norm.hi)[2].cpu().numpy()]

    def sample(self, n: int):
        """n rays: origins, directions, near, far, target colours (n x 3 in [0, 1]) and mask labels."""
        n_bg = int(round(n * self.cfg.background_fraction)) if len(self.bg) else 0
        pick_fg = torch.randint(len(self.fg), (n - n_bg,), device=self.device)
        pick_bg = torch.randint(max(len(self.bg), 1), (n_bg,), device=self.device)
        o, d, near, far, rgb = self.rays(torch.cat([self.fg[pick_fg], self.bg[pick_bg]]))
        return o, d, near, far, rgb, torch.arange(n, device=self.device) < n - n_bg

    def rays(self, flat: torch.Tensor):
        """Origins, directions, near, far and colours (in [0, 1]) of flat pixel indices (view, row, column)."""
        view, pixel = flat // (self.h * self.w), flat % (self.h * self.w)
        u, v = (pixel % self.w).float(), (pixel // self.w).float()
        o, d = camera_rays(self.K, self.poses[view], u, v, self.norm, self.device)
        near, far, _ = box_intersect(o, d, self.norm.lo, self.norm.hi)
        return o, d, near, far, self.rgb[flat].float() / 255.0


def _identity(cfg: NeusConfig, train: Views, aabb: np.ndarray) -> dict:
    """What a checkpoint must match to be resumed: the config, the box and a fingerprint of the views."""
    digest = hashlib.sha1()
    for array in (train.K, train.T_turntable_cam, train.rgb[:, ::7, ::7], train.masks[:, ::7, ::7]):
        digest.update(np.ascontiguousarray(array).tobytes())
    config = {k: v for k, v in asdict(cfg).items() if k not in _NOT_IDENTITY}
    return {"config": config, "aabb": np.round(np.asarray(aabb, dtype=float), 9).tolist(),
            "views": digest.hexdigest(), "names": list(train.names)}


def _lr_factor(cfg: NeusConfig, step: int) -> float:
    if step < cfg.warmup_steps:
        return (step + 1) / cfg.warmup_steps
    progress = (step - cfg.warmup_steps) / max(cfg.steps - cfg.warmup_steps, 1)
    return cfg.lr_final_factor + (1 - cfg.lr_final_factor) * 0.5 * (1 + math.cos(math.pi * min(progress, 1.0)))


def _optimizer(net: NeusNetwork, cfg: NeusConfig) -> torch.optim.Adam:
    others = [p for name, p in net.named_parameters() if name != "variance"]
    groups = [{"params": others, "lr": cfg.lr, "base_lr": cfg.lr},
              {"params": [net.variance], "lr": cfg.lr_variance, "base_lr": cfg.lr_variance}]
    fused = {"fused": True} if _fused_ok(net) else {}
    return torch.optim.Adam(groups, betas=(0.9, 0.99), eps=1e-15, **fused)


def _fused_ok(net: NeusNetwork) -> bool:
    """Fused Adam: one pass over the large hash table instead of several (CPU since torch 2.4, CUDA)."""
    try:
        torch.optim.Adam([torch.nn.Parameter(torch.zeros(1, device=net.variance.device))], fused=True)
        return True
    except (RuntimeError, TypeError):
        return False


def pretrain_sdf(net: NeusNetwork, init_sdf: Callable[[np.ndarray], np.ndarray], norm: Normaliser,
                 cfg: NeusConfig, rng: np.random.Generator) -> float:
    """Fit the SDF network to `init_sdf` (metres) inside the box; returns the last loss."""
    device = net.variance.device
    lo, hi = norm.lo, norm.hi
    uniform = rng.uniform(lo, hi, size=(max(8 * cfg.pretrain_points, 32768), 3))
    target = np.asarray(init_sdf(uniform * norm.scale_m + norm.centre), dtype=np.float64) / norm.scale_m
    near = uniform[np.argsort(np.abs(target))[: len(uniform) // 2]]
    near = np.clip(near + rng.normal(0, 0.02, near.shape), lo, hi)
    near_target = np.asarray(init_sdf(near * norm.scale_m + norm.centre), dtype=np.float64) / norm.scale_m
    pts = torch.as_tensor(np.concatenate([uniform, near]), dtype=torch.float32, device=device)
    tgt = torch.as_tensor(np.concatenate([target, near_target]), dtype=torch.float32, device=device)
    trunc = cfg.pretrain_truncation
    params = [net.grid.table, *net.sdf_layers.parameters()]
    opt = torch.optim.Adam(params, lr=cfg.lr, betas=(0.9, 0.99), eps=1e-15)
    loss = torch.zeros(())
    for _ in range(cfg.pretrain_steps):
        pick = torch.randint(len(pts), (cfg.pretrain_points,), device=device)
        geo = net.geometry(pts[pick], gradient=True)
        fit = (geo.sdf.clamp(-trunc, trunc) - tgt[pick].clamp(-trunc, trunc)).abs().mean()
        loss = fit + cfg.eikonal_weight * ((geo.grad.norm(dim=-1) - 1.0) ** 2).mean()
        opt.zero_grad(set_to_none=False)
        loss.backward()
        opt.step()
    return float(loss.detach())


class TextureRays:
    """Every training mask pixel with its cached surface samples, for the appearance stage."""

    def __init__(self, net: NeusNetwork, sampler: RaySampler, spec: RenderSpec, k: int, chunk: int = 4096):
        points, normals, weights, dirs = [], [], [], []
        for s in range(0, len(sampler.fg), chunk):
            o, d, near, far, _ = sampler.rays(sampler.fg[s:s + chunk])
            x, n, w = surface_samples(net, o, d, near, far, spec, k)
            points.append(x)
            normals.append(n)
            weights.append(w)
            dirs.append(d)
        self.points, self.normals = torch.cat(points), torch.cat(normals)
        self.weights, self.dirs = torch.cat(weights), torch.cat(dirs)
        self.rgb = sampler.rgb[sampler.fg]
        """Target colours, uint8."""

    def loss(self, net: NeusNetwork, n: int) -> torch.Tensor:
        """Colour MSE of n random mask rays rendered from their cached samples (geometry frozen)."""
        pick = torch.randint(len(self.rgb), (n,), device=self.rgb.device)
        k = self.points.shape[1]
        with torch.no_grad():
            geo = net.geometry(self.points[pick].view(-1, 3))
        dirs = self.dirs[pick][:, None, :].expand(n, k, 3).reshape(-1, 3)
        colour = net.colour(geo, self.normals[pick].view(-1, 3), dirs).view(n, k, 3)
        rgb = (colour * self.weights[pick][..., None]).sum(1)
        return functional.mse_loss(rgb, self.rgb[pick].float() / 255.0)


def _texture_optimizer(net: NeusNetwork, cfg: NeusConfig) -> torch.optim.Adam:
    params = [*net.colour_layers.parameters()] + ([net.colour_grid.table] if net.colour_grid is not None else [])
    fused = {"fused": True} if _fused_ok(net) else {}
    return torch.optim.Adam([{"params": params, "lr": cfg.texture_lr, "base_lr": cfg.texture_lr}],
                            betas=(0.9, 0.99), eps=1e-15, **fused)


def _texture_lr_factor(cfg: NeusConfig, step: int) -> float:
    progress = step / max(cfg.texture_steps, 1)
    return cfg.lr_final_factor + (1 - cfg.lr_final_factor) * 0.5 * (1 + math.cos(math.pi * min(progress, 1.0)))


def train_neus(train: Views, aabb: np.ndarray, cfg: NeusConfig, *, workdir: Path,
               init_sdf: Callable[[np.ndarray], np.ndarray] | None = None,
               progress: ProgressFn = no_progress, cancel: threading.Event | None = None) -> NeusField:
    """Train a NeuS field on `train` views inside `aabb` (2 x 3 [min, max], turntable frame, metres).

    init_sdf: optional signed distance (metres, negative inside) of a coarse shape to pretrain the SDF to.
    Steps count on through the appearance stage (cfg.steps + cfg.texture_steps in all). Checkpoints go to
    workdir/neus.pt every cfg.checkpoint_every steps, on cancel and at the end; a call finding a checkpoint
    of the same config, box and views resumes from it (a finished one just loads).
    Raises Cancelled when `cancel` is set (after saving) and N2DError when the loss stops being finite.
    """
    workdir = Path(workdir)
    path = workdir / CHECKPOINT
    device = resolve_device(cfg.device)
    torch.manual_seed(cfg.seed)
    norm = Normaliser.from_aabb(aabb)
    net = NeusNetwork(cfg.field_spec()).to(device)
    field = NeusField(net, aabb, cfg.render_spec(), str(device))
    identity = _identity(cfg, train, aabb)
    total = cfg.steps + cfg.texture_steps
    start = 0
    state = load_checkpoint(path, device) if path.is_file() else None
    resumed = state is not None and state.get("identity") == identity
    if resumed:
        net.load_state_dict(state["network"])
        start = int(state["step"])
    elif init_sdf is not None:
        progress(Progress(0.0, "neus", message="fitting the SDF to the initial shape"))
        pretrain_sdf(net, init_sdf, norm, cfg, np.random.default_rng(cfg.seed))
    opt = _optimizer(net, cfg) if start < cfg.steps else _texture_optimizer(net, cfg)
    if resumed and state.get("stage") == ("neus" if start < cfg.steps else "texture"):
        opt.load_state_dict(state["optimizer"])

    def save(step: int) -> None:
        atomic_torch_save({**field.state(), "identity": identity, "step": step, "optimizer": opt.state_dict(),
                           "stage": "neus" if step < cfg.steps else "texture"}, path)

    sampler = RaySampler(train, norm, cfg, device)
    spec = cfg.render_spec()
    texture = None
    eta = Eta()
    info = {"step": start, "steps": total, "loss": float("nan"), "psnr": float("nan")}
    progress(Progress(start / max(total, 1), "neus", message=f"starting at step {start}/{total}",
                      info=dict(info)))
    net.train()
    for step in range(start, total):
        if cancel is not None and cancel.is_set():
            save(step)
            raise Cancelled(f"NeuS training cancelled at step {step}/{total}", f"re-run to resume from step {step}")
        torch.manual_seed(cfg.seed * 1_000_003 + step)
        if step < cfg.steps:
            loss, colour = _neus_step(net, opt, sampler, spec, cfg, step)
        else:
            if step == cfg.steps and start < cfg.steps:
                opt = _texture_optimizer(net, cfg)
            if texture is None:
                progress(Progress(step / total, "neus", message="caching surface samples for the appearance stage",
                                  info=dict(info)))
                texture = TextureRays(net, sampler, spec, cfg.texture_samples)
            for group in opt.param_groups:
                group["lr"] = group["base_lr"] * _texture_lr_factor(cfg, step - cfg.steps)
            loss = colour = texture.loss(net, cfg.texture_rays)
        value = float(loss.detach())
        if not math.isfinite(value):
            raise N2DError(f"NeuS training diverged at step {step} (loss {value})",
                           f"lower the learning rate (lr={cfg.lr:g}) or raise warmup_steps; re-run")
        opt.zero_grad(set_to_none=False)
        loss.backward()
        opt.step()
        done = step + 1
        if done % cfg.progress_every == 0 or done == total:
            info.update(step=done, loss=value, psnr=-10.0 * math.log10(max(float(colour.detach()), 1e-10)),
                        inv_s=float(net.inv_s().detach()))
            progress(Progress(done / total, "neus", eta(done / total), f"step {done}/{total} loss {value:.4f}",
                              dict(info)))
        if done % cfg.checkpoint_every == 0 and done < total:
            save(done)
    if not resumed or start < total:
        save(total)
    net.eval()
    return field


def _neus_step(net: NeusNetwork, opt, sampler: RaySampler, spec: RenderSpec, cfg: NeusConfig, step: int):
    """Loss (and colour loss) of one NeuS batch; sets the learning rates and coarse-to-fine levels."""
    for group in opt.param_groups:
        group["lr"] = group["base_lr"] * _lr_factor(cfg, step)
    if cfg.level_every_steps > 0:
        net.set_level_mask(cfg.level_start + step / cfg.level_every_steps)
    o, d, near, far, target, label = sampler.sample(cfg.rays)
    out = render_rays(net, o, d, near, far, spec, jitter=True, cos_anneal=min(1.0, step / max(cfg.cos_anneal_steps, 1)))
    colour = functional.mse_loss(out.rgb[label], target[label])
    acc = out.acc.clamp(1e-3, 1 - 1e-3)  # binary cross-entropy, written out so NaN reaches the caller's check
    mask = -torch.where(label, acc.log(), (1 - acc).log()).mean()
    eikonal = ((out.grad.norm(dim=-1) - 1.0) ** 2).mean()
    loss = colour + cfg.mask_weight * mask + cfg.eikonal_weight * eikonal
    if cfg.smooth_weight > 0:
        loss = loss + cfg.smooth_weight * _smoothness(net, o, d, out, label, cfg.smooth_radius_m / sampler.norm.scale_m,
                                                      cfg.smooth_edge_deg)
    return loss, colour


def _smoothness(net: NeusNetwork, o, d, out, label, radius: float, edge_deg: float = 0.0) -> torch.Tensor:
    """UNISURF's surface smoothness: mean |n(x) - n(x + e)| at the expected surface points x of the mask rays
    that reach an opaque surface, e ~ N(0, radius) (normalised units). With edge_deg > 0 each term is truncated
    at the chord 2 sin(edge_deg / 2) of unit normals that far apart."""
    hit = label & (out.acc.detach() > 0.5)
    if not bool(hit.any()):
        return torch.zeros((), device=o.device)
    x = (o[hit] + d[hit] * (out.depth[hit] / out.acc[hit]).detach()[:, None])
    grad = net.geometry(torch.cat([x, x + torch.randn_like(x) * radius]), gradient=True).grad
    normals = functional.normalize(grad, dim=-1)
    gaps = (normals[: len(x)] - normals[len(x):]).norm(dim=-1)
    if edge_deg > 0:
        gaps = gaps.clamp(max=2.0 * math.sin(math.radians(edge_deg) / 2.0))
    return gaps.mean()
