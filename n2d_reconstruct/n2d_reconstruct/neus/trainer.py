"""NeuS training: configuration and presets, ray batches from masked views, losses, checkpoints, resume.

Losses per batch: colour (mean squared error, sRGB [0, 1], composited on black) on rays whose pixel is in
the object mask only; mask (binary cross-entropy between accumulated opacity and the mask) on all rays, so
background rays clear the free space; eikonal on every differentiable sample; surface smoothness (UNISURF,
capped at edges; on in the cpu and gpu presets) at the mask rays' surface points. Rays come mostly from mask
pixels, the rest from background pixels inside each view's dilated mask bounding box whose rays cross the
object's box. With `init_sdf` the SDF network is first fitted to that shape (truncated L1 + eikonal).
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import threading
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional

from n2d_common.config import check_ranges, from_dict
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
class AppearanceConfig:
    """The appearance stage after the NeuS steps: geometry frozen, colour fitted on cached surface samples."""

    steps: int = 0
    """Appearance steps after the NeuS steps (0: none)."""
    rays: int = 8192
    """Rays per appearance step."""
    samples: int = 4
    """Heaviest sections per ray cached for the appearance stage."""
    lr: float = 1e-2
    """Peak learning rate of the appearance stage (cosine decay to optim.lr_final_factor of it)."""

    def __post_init__(self):
        check_ranges(self, positive=("rays", "samples", "lr"), non_negative=("steps",))


@dataclass
class PretrainConfig:
    """Fitting the SDF network to an initial shape (init_sdf, when given) before the NeuS steps."""

    steps: int = 300
    """Steps fitting the SDF to init_sdf."""
    points: int = 8192
    """Points per pretraining step."""
    truncation: float = 0.1
    """Pretraining compares SDFs clamped to +- this (normalised units)."""

    def __post_init__(self):
        check_ranges(self, positive=("points", "truncation"), non_negative=("steps",))


@dataclass
class SamplerConfig(RenderSpec):
    """Training rays: how many per batch and where they come from, and (from RenderSpec) the samples per ray."""

    rays: int = 1024
    """Rays per training batch."""
    background_fraction: float = 0.2
    """Share of each batch's rays drawn from background pixels (mask loss only)."""
    bbox_margin: float = 0.25
    """Background rays come from each view's mask bounding box grown by this fraction of its size."""

    def __post_init__(self):
        super().__post_init__()
        check_ranges(self, positive=("rays",), non_negative=("bbox_margin",))
        if not 0 <= self.background_fraction < 1:
            raise ValueError(f"background_fraction must be in [0, 1), got {self.background_fraction!r}")


@dataclass
class OptimiserConfig:
    """Adam's learning rates and their schedule, NeuS's cosine annealing and the coarse-to-fine hash levels."""

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
    level_start: int = 0
    """Coarse-to-fine: active hash levels at step 0 (0 = all levels from the start)."""
    level_every_steps: int = 0
    """Coarse-to-fine: steps until the next level is fully active."""

    def __post_init__(self):
        check_ranges(self, positive=("lr",), non_negative=("lr_variance", "warmup_steps", "cos_anneal_steps",
                                                           "level_start", "level_every_steps"))
        if not 0 <= self.lr_final_factor <= 1:
            raise ValueError(f"lr_final_factor must be in [0, 1], got {self.lr_final_factor!r}")


@dataclass
class LossConfig:
    """Weights of the losses besides the colour loss."""

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

    def __post_init__(self):
        check_ranges(self, positive=("smooth_radius_m",),
                     non_negative=("eikonal_weight", "mask_weight", "smooth_weight", "smooth_edge_deg"))
        if not self.smooth_edge_deg <= 180:
            raise ValueError(f"smooth_edge_deg must be in [0, 180] degrees, got {self.smooth_edge_deg!r}")


@dataclass
class NeusConfig:
    """Every tunable of NeuS training: the user's settings here, the advanced ones in a section each.
    Distances are in the network frame unless named _m (metres)."""

    steps: int = 5000
    """Training steps (batches)."""
    device: str = "auto"
    """"auto" (CUDA when available), "cpu" or "cuda"."""
    seed: int = 0
    """Seed of weights, ray batches and samples."""
    field: FieldSpec = dataclasses.field(default_factory=FieldSpec)
    """The networks: hash grid, SDF and colour MLPs, initial sphere and variance."""
    sampler: SamplerConfig = dataclasses.field(default_factory=SamplerConfig)
    """Rays per batch and samples per ray."""
    optim: OptimiserConfig = dataclasses.field(default_factory=OptimiserConfig)
    """Learning rates and schedules."""
    loss: LossConfig = dataclasses.field(default_factory=LossConfig)
    """Loss weights."""
    appearance: AppearanceConfig = dataclasses.field(default_factory=AppearanceConfig)
    """The appearance stage after the NeuS steps."""
    pretrain: PretrainConfig = dataclasses.field(default_factory=PretrainConfig)
    """Pretraining the SDF to the initial shape."""
    checkpoint_every: int = 500
    """Steps between checkpoints (also written on cancel and at the end)."""
    progress_every: int = 10
    """Steps between progress reports."""

    def __post_init__(self):
        check_ranges(self, positive=("checkpoint_every", "progress_every"), non_negative=("steps",))
        try:
            resolve_device(self.device)
        except RuntimeError as exc:
            raise ValueError(f"device {self.device!r}: {exc}; use \"auto\", \"cpu\" or \"cuda\"") from None

    @classmethod
    def preset(cls, name: str) -> NeusConfig:
        """"tiny" (tests, seconds on CPU), "cpu" (2 cores, tens of minutes) or "gpu" (the paper's scale)."""
        if name not in PRESETS:
            raise N2DError(f"unknown NeuS preset {name!r}", f"use one of {', '.join(PRESETS)}")
        return from_dict(cls, PRESETS[name], f"NeuS preset {name}")

    def render_spec(self) -> RenderSpec:
        """The samples per ray (the renderer's part of the sampler section)."""
        return RenderSpec(**{f.name: getattr(self.sampler, f.name) for f in dataclasses.fields(RenderSpec)})


PRESETS: dict[str, dict] = {
    "tiny": {"field": dict(levels=8, log2_table=14, base_res=8, max_res=128, sdf_hidden=32, geo_features=7,
                           colour_hidden=32, colour_layers=1),
             "sampler": dict(rays=256, coarse_samples=16, importance_samples=16, up_sample_steps=2, coarse_every=4),
             "optim": dict(warmup_steps=20, cos_anneal_steps=100, lr_variance=3e-3),
             "pretrain": dict(steps=100, points=2048),
             "steps": 300, "checkpoint_every": 100},
    "cpu": {"field": dict(levels=16, log2_table=18, max_res=1024),
            "sampler": dict(rays=1024, coarse_samples=32, importance_samples=32, up_sample_steps=4, coarse_every=4),
            "optim": dict(warmup_steps=200, cos_anneal_steps=1000),
            "loss": dict(smooth_weight=0.01, smooth_edge_deg=30.0),
            "appearance": dict(steps=1500),
            "pretrain": dict(steps=300),
            "steps": 6000, "checkpoint_every": 500},
    "gpu": {"field": dict(levels=16, log2_table=19, max_res=2048),
            "sampler": dict(rays=4096, coarse_samples=64, importance_samples=64, up_sample_steps=4, coarse_every=1),
            "optim": dict(warmup_steps=500, cos_anneal_steps=5000),
            "loss": dict(smooth_weight=0.01, smooth_edge_deg=30.0),
            "pretrain": dict(steps=1000, points=65536),
            "steps": 20000, "checkpoint_every": 2000},
}
"""Overrides of the defaults per preset, section by section."""

_NOT_IDENTITY = ("device", "checkpoint_every", "progress_every")
"""Config fields that do not change the result: a checkpoint written with other values still resumes."""


class RaySampler:
    """Random training rays: pixel colours, mask labels, origins and directions (normalised frame)."""

    def __init__(self, views: Views, norm: Normaliser, cfg: SamplerConfig, device: torch.device):
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
    if step < cfg.optim.warmup_steps:
        return (step + 1) / cfg.optim.warmup_steps
    warmup = cfg.optim.warmup_steps
    return _cosine(cfg.optim.lr_final_factor, (step - warmup) / max(cfg.steps - warmup, 1))


def _cosine(final: float, progress: float) -> float:
    """Cosine decay from 1 at progress 0 to `final` at progress 1 (and after)."""
    return final + (1 - final) * 0.5 * (1 + math.cos(math.pi * min(progress, 1.0)))


def _optimizer(net: NeusNetwork, cfg: NeusConfig) -> torch.optim.Adam:
    others = [p for name, p in net.named_parameters() if name != "variance"]
    groups = [{"params": others, "lr": cfg.optim.lr, "base_lr": cfg.optim.lr},
              {"params": [net.variance], "lr": cfg.optim.lr_variance, "base_lr": cfg.optim.lr_variance}]
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
    uniform = rng.uniform(lo, hi, size=(max(8 * cfg.pretrain.points, 32768), 3))
    target = np.asarray(init_sdf(uniform * norm.scale_m + norm.centre), dtype=np.float64) / norm.scale_m
    near = uniform[np.argsort(np.abs(target))[: len(uniform) // 2]]
    near = np.clip(near + rng.normal(0, 0.02, near.shape), lo, hi)
    near_target = np.asarray(init_sdf(near * norm.scale_m + norm.centre), dtype=np.float64) / norm.scale_m
    pts = torch.as_tensor(np.concatenate([uniform, near]), dtype=torch.float32, device=device)
    tgt = torch.as_tensor(np.concatenate([target, near_target]), dtype=torch.float32, device=device)
    trunc = cfg.pretrain.truncation
    params = [net.grid.table, *net.sdf_layers.parameters()]
    opt = torch.optim.Adam(params, lr=cfg.optim.lr, betas=(0.9, 0.99), eps=1e-15)
    loss = torch.zeros(())
    for _ in range(cfg.pretrain.steps):
        pick = torch.randint(len(pts), (cfg.pretrain.points,), device=device)
        geo = net.geometry(pts[pick], gradient=True)
        fit = (geo.sdf.clamp(-trunc, trunc) - tgt[pick].clamp(-trunc, trunc)).abs().mean()
        loss = fit + cfg.loss.eikonal_weight * ((geo.grad.norm(dim=-1) - 1.0) ** 2).mean()
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
    return torch.optim.Adam([{"params": params, "lr": cfg.appearance.lr, "base_lr": cfg.appearance.lr}],
                            betas=(0.9, 0.99), eps=1e-15, **fused)


def _texture_lr_factor(cfg: NeusConfig, step: int) -> float:
    return _cosine(cfg.optim.lr_final_factor, step / max(cfg.appearance.steps, 1))


def train_neus(train: Views, aabb: np.ndarray, cfg: NeusConfig, *, workdir: Path,
               init_sdf: Callable[[np.ndarray], np.ndarray] | None = None,
               progress: ProgressFn = no_progress, cancel: threading.Event | None = None) -> NeusField:
    """Train a NeuS field on `train` views inside `aabb` (2 x 3 [min, max], turntable frame, metres).

    init_sdf: optional signed distance (metres, negative inside) of a coarse shape to pretrain the SDF to.
    Steps count on through the appearance stage (cfg.steps + cfg.appearance.steps in all). Checkpoints go to
    workdir/neus.pt every cfg.checkpoint_every steps, on cancel, on Ctrl-C (KeyboardInterrupt, re-raised) and at
    the end; a call finding a checkpoint of the same config, box and views resumes from it (a finished one just
    loads).
    Raises Cancelled when `cancel` is set (after saving) and N2DError when the loss stops being finite.
    """
    workdir = Path(workdir)
    path = workdir / CHECKPOINT
    device = resolve_device(cfg.device)
    torch.manual_seed(cfg.seed)
    norm = Normaliser.from_aabb(aabb)
    net = NeusNetwork(cfg.field).to(device)
    field = NeusField(net, aabb, cfg.render_spec(), str(device))
    identity = _identity(cfg, train, aabb)
    total = cfg.steps + cfg.appearance.steps
    start = 0
    state = load_checkpoint(path, device) if path.is_file() else None
    resumed = state is not None and state.get("identity") == identity
    if resumed:
        net.load_state_dict(state["network"])
        start = int(state["step"])
    elif init_sdf is not None:
        progress(Progress(0.0, "neus", message="fitting the SDF to the initial shape"))
        pretrain_sdf(net, init_sdf, norm, cfg, np.random.default_rng(cfg.seed))
    # whose optimizer `opt` is: a checkpoint at step cfg.steps still holds the NeuS one (the appearance stage
    # starts its own on its first step, a resumed run too), and says so
    opt_stage = "neus" if start < cfg.steps else "texture"
    opt = _optimizer(net, cfg) if opt_stage == "neus" else _texture_optimizer(net, cfg)
    if (resumed and state.get("stage") == opt_stage
            and len(state["optimizer"]["param_groups"]) == len(opt.param_groups)):  # older checkpoints: not always
        opt.load_state_dict(state["optimizer"])

    def save(step: int) -> None:
        atomic_torch_save({**field.state(), "identity": identity, "step": step, "optimizer": opt.state_dict(),
                           "stage": opt_stage}, path)

    sampler = RaySampler(train, norm, cfg.sampler, device)
    spec = cfg.render_spec()
    texture = None
    eta = Eta()
    info = {"step": start, "steps": total, "loss": float("nan"), "psnr": float("nan")}
    progress(Progress(start / max(total, 1), "neus", message=f"starting at step {start}/{total}",
                      info=dict(info)))
    net.train()
    done, updating = start, False
    try:
        for step in range(start, total):
            if cancel is not None and cancel.is_set():
                save(step)
                raise Cancelled(f"NeuS training cancelled at step {step}/{total}", f"re-run to resume from step {step}")
            torch.manual_seed(cfg.seed * 1_000_003 + step)
            if step < cfg.steps:
                loss, colour = _neus_step(net, opt, sampler, spec, cfg, step)
            else:
                if step == cfg.steps and start < cfg.steps:
                    opt, opt_stage = _texture_optimizer(net, cfg), "texture"
                if texture is None:
                    progress(Progress(step / total, "neus", message="caching surface samples for the appearance stage",
                                      info=dict(info)))
                    texture = TextureRays(net, sampler, spec, cfg.appearance.samples)
                for group in opt.param_groups:
                    group["lr"] = group["base_lr"] * _texture_lr_factor(cfg, step - cfg.steps)
                loss = colour = texture.loss(net, cfg.appearance.rays)
            value = float(loss.detach())
            if not math.isfinite(value):
                raise N2DError(f"NeuS training diverged at step {step} (loss {value})",
                               f"lower the learning rate (lr={cfg.optim.lr:g}) or raise optim.warmup_steps; re-run")
            opt.zero_grad(set_to_none=False)
            loss.backward()
            updating = True  # an interrupt inside the update leaves the weights half stepped: not saved
            opt.step()
            updating, done = False, step + 1
            if done % cfg.progress_every == 0 or done == total:
                info.update(step=done, loss=value, psnr=-10.0 * math.log10(max(float(colour.detach()), 1e-10)),
                            inv_s=float(net.inv_s().detach()))
                progress(Progress(done / total, "neus", eta(done / total), f"step {done}/{total} loss {value:.4f}",
                                  dict(info)))
            if done % cfg.checkpoint_every == 0 and done < total:
                save(done)
    except KeyboardInterrupt:  # Ctrl-C (the CLI's SIGINT): keep the steps done since the last checkpoint
        if not updating and done > start:
            save(done)
        raise
    if not resumed or start < total:
        save(total)
    net.eval()
    return field


def _neus_step(net: NeusNetwork, opt, sampler: RaySampler, spec: RenderSpec, cfg: NeusConfig, step: int):
    """Loss (and colour loss) of one NeuS batch; sets the learning rates and coarse-to-fine levels."""
    for group in opt.param_groups:
        group["lr"] = group["base_lr"] * _lr_factor(cfg, step)
    if cfg.optim.level_every_steps > 0:
        net.set_level_mask(cfg.optim.level_start + step / cfg.optim.level_every_steps)
    o, d, near, far, target, label = sampler.sample(cfg.sampler.rays)
    anneal = min(1.0, step / max(cfg.optim.cos_anneal_steps, 1))
    out = render_rays(net, o, d, near, far, spec, jitter=True, cos_anneal=anneal)
    colour = functional.mse_loss(out.rgb[label], target[label])
    acc = out.acc.clamp(1e-3, 1 - 1e-3)  # binary cross-entropy, written out so NaN reaches the caller's check
    mask = -torch.where(label, acc.log(), (1 - acc).log()).mean()
    eikonal = ((out.grad.norm(dim=-1) - 1.0) ** 2).mean()
    weights = cfg.loss
    loss = colour + weights.mask_weight * mask + weights.eikonal_weight * eikonal
    if weights.smooth_weight > 0:
        loss = loss + weights.smooth_weight * _smoothness(net, o, d, out, label,
                                                          weights.smooth_radius_m / sampler.norm.scale_m,
                                                          weights.smooth_edge_deg)
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
