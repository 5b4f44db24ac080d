"""Stage 2 of the mesh (as nerf2mesh's): vertex offsets and an appearance model fitted to the photos by
differentiable rendering, in pure PyTorch on the CPU rasteriser.

On a turntable the object turns under lights that stand still with the camera, so in the camera frame every
view has the same light. The appearance model is

    colour = albedo(vertex) * shading(n_cam) + specular(vertex) * highlights(r_cam)

with a per-vertex albedo and specular strength (interpolated by barycentrics), `shading` a second-order
spherical-harmonics function of the surface normal in the camera frame (smooth: the diffuse light) and
`highlights` a few spherical Gaussian lobes of the reflected view direction (sharp: the lights' mirror images on
glossy parts). One light for all views makes shading evidence of the normal: a flat top keeps its brightness as
the plate turns, the tilted facets of a visual hull's roof over it do not, so plain surfaces that give
photo-consistency nothing to match still settle.

Each iteration renders one training view. The rasteriser gives each pixel its face (no gradient); the ray through
the pixel is intersected with that face's current vertices (Moller-Trumbore, differentiable), so the
barycentrics, and with them the interpolated colour and normal, depend on the vertices, as in a differentiable
rasteriser's interpolation. The vertices on the rendered outline are drawn to the photo's mask outline (its
signed distance, sampled bilinearly at their projection). A uniform Laplacian on the offsets keeps the surface
smooth; vertices on the plate cut stay where they are.

The exported albedo is baked from the photos with the fitted highlights subtracted (`specular_images`), so it
carries no highlights; `render` draws the fitted model in any view (the held-out views' "stage 2" scores).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import torch
import trimesh
from torch.nn import functional as F  # noqa: N812 (PyTorch's own spelling)

from n2d_common.frames import inv_T, transform_points
from n2d_common.progress import Progress, ProgressFn, no_progress
from n2d_common.raster import rasterize
from n2d_reconstruct.data import Views
from n2d_reconstruct.hull import signed_distance_px

SDF_CLAMP_PX = 20.0
"""The mask outline's signed distance is clamped to this (pixels): a vertex far outside is pulled, not flung."""
DEPTH_TOLERANCE_PX = 2.0
"""A vertex is visible in a view when its depth is within this many pixels on the object of the rendered depth."""


@dataclass
class Stage2Config:
    """Vertex offsets and appearance fitted by differentiable rendering (both methods)."""

    enabled: bool = False
    """Run stage 2 after the surface phase (refine on the fast path, fair on NeuS)."""
    iterations: int = 300
    """Optimisation steps, one training view each (views taken in shuffled rounds)."""
    warmup: int = 60
    """First steps that fit the appearance alone: a light still unknown would otherwise be explained by tilting
    the surface."""
    pixels: int = 12000
    """Pixels of the object sampled per step."""
    step_px: float = 0.25
    """Adam step of the vertex offsets at the start, in pixels on the object (the size of a pixel at the object's
    distance); it decays to `final_step` of that by a cosine."""
    final_step: float = 0.1
    """The offsets' last step as a share of the first."""
    appearance_lr: float = 0.03
    """Adam learning rate of the appearance (albedo and specular logits, light, lobes)."""
    silhouette: float = 0.02
    """Weight of the outline term (squared pixels) against the photometric one."""
    smoothness: float = 2.0
    """Weight of the uniform Laplacian of the offsets (squared pixels)."""
    lobes: int = 3
    """Spherical Gaussian highlight lobes (0: a diffuse model)."""
    specular_l1: float = 0.002
    """Sparsity weight on the specular strength: highlights where the photos need them, not everywhere."""
    huber: float = 0.05
    """Photometric loss is Huber with this transition (colours in 0..1): robust to shadows the model lacks."""
    rim_cos: float = 0.3
    """Vertices whose normal is closer than this cosine to perpendicular to the view ray are outline candidates."""
    face_normals: bool = True
    """Shade with each face's own normal (its gradient is direct and local: what shading says of a facet moves that
    facet; sharp edges stay sharp) rather than interpolated vertex normals."""
    seed: int = 0
    """Random seed of the view order and pixel samples."""

    def __post_init__(self):
        if self.iterations < 1 or self.pixels < 16 or not 0 <= self.warmup < self.iterations:
            raise ValueError("stage2.iterations must be >= 1, stage2.pixels >= 16 and stage2.warmup in "
                             "[0, iterations)")
        if self.step_px <= 0 or not 0 < self.final_step <= 1:
            raise ValueError("stage2.step_px must be > 0 and stage2.final_step in (0, 1]")
        if min(self.silhouette, self.smoothness, self.specular_l1, self.appearance_lr) < 0 or self.huber <= 0:
            raise ValueError("stage2 weights must be >= 0 and stage2.huber > 0")
        if self.lobes < 0 or not 0 < self.rim_cos < 1:
            raise ValueError("stage2.lobes must be >= 0 and stage2.rim_cos in (0, 1)")


def _sh(n: torch.Tensor) -> torch.Tensor:
    """N x 9 real spherical harmonics basis up to order 2 (constants folded into the coefficients)."""
    x, y, z = n.unbind(-1)
    return torch.stack([torch.ones_like(x), y, z, x, x * y, y * z, 3 * z * z - 1, x * z, x * x - y * y], -1)


def _vertex_normals(v: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
    """V x 3 area-weighted unit vertex normals."""
    fn = torch.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]], dim=1)
    vn = torch.zeros_like(v)
    for k in range(3):
        vn = vn.index_add(0, f[:, k], fn)
    return F.normalize(vn, dim=1, eps=1e-12)


def _laplacian(faces: np.ndarray, n: int) -> torch.Tensor:
    """Sparse V x V row-normalised adjacency of the mesh's edges (x - A x is the uniform Laplacian)."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.unique(np.sort(e, axis=1), axis=0)
    rows, cols = np.concatenate([e[:, 0], e[:, 1]]), np.concatenate([e[:, 1], e[:, 0]])
    deg = np.bincount(rows, minlength=n).astype(np.float64)
    w = 1.0 / np.maximum(deg[rows], 1.0)
    return torch.sparse_coo_tensor(np.stack([rows, cols]), w.astype(np.float32), (n, n)).coalesce()


class Appearance(torch.nn.Module):
    """The fitted appearance: per-vertex albedo and specular strength, the camera-frame light and highlights."""

    def __init__(self, albedo: np.ndarray, lobes: int):
        super().__init__()
        a = np.clip(albedo, 0.02, 0.98)
        self.albedo_logit = torch.nn.Parameter(torch.as_tensor(np.log(a / (1 - a)), dtype=torch.float32))
        self.specular_logit = torch.nn.Parameter(torch.full((len(albedo),), -6.0))
        # The diffuse light, second-order spherical harmonics of the camera-frame normal: as smooth as a Lambertian
        # surface's irradiance is, so the sharp highlights are left to the lobes. It starts at 1 everywhere.
        light = torch.zeros(9, 3)
        light[0] = 1.0
        self.light = torch.nn.Parameter(light)
        # Lobes start toward the camera and up (camera frame: x right, y down, z forward), spread left and right.
        start = torch.tensor([[-0.5, -0.5, -0.7], [0.5, -0.5, -0.7], [0.0, -0.8, -0.6], [0.0, 0.0, -1.0]])
        self.lobe_dir = torch.nn.Parameter(start[np.arange(lobes) % len(start)].clone())
        self.lobe_sharpness = torch.nn.Parameter(torch.full((lobes,), 3.5))  # exp: about 33
        self.lobe_amplitude = torch.nn.Parameter(torch.zeros(lobes))

    def colour(self, faces_v: torch.Tensor, bary: torch.Tensor, n_cam: torch.Tensor, r_cam: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor]:
        """(N x 3 predicted colour in 0..1, N x 3 its specular part) of N surface points: `faces_v` N x 3 vertex
        indices, `bary` N x 3 weights, unit normal and reflected view direction in the camera frame."""
        albedo = (torch.sigmoid(self.albedo_logit)[faces_v] * bary[..., None]).sum(1)
        diffuse = albedo * self.shading(n_cam)
        return diffuse + (spec := self.specular(faces_v, bary, r_cam)), spec

    def shading(self, n_cam: torch.Tensor) -> torch.Tensor:
        """N x 3 diffuse light arriving at surfaces of camera-frame normals `n_cam`."""
        return (_sh(n_cam) @ self.light).clamp_min(0.0)

    def specular(self, faces_v: torch.Tensor, bary: torch.Tensor, r_cam: torch.Tensor) -> torch.Tensor:
        strength = (F.softplus(self.specular_logit)[faces_v] * bary).sum(1)
        if not len(self.lobe_amplitude):
            return torch.zeros(len(r_cam), 3)
        mu = F.normalize(self.lobe_dir, dim=1)
        lobes = F.softplus(self.lobe_amplitude) * torch.exp(torch.exp(self.lobe_sharpness) * (r_cam @ mu.T - 1.0))
        return (strength * lobes.sum(1))[:, None].expand(-1, 3)


@dataclass
class Stage2Result:
    """What stage 2 fitted: the mesh it moved (turntable frame) and the appearance on its vertices."""

    vertices: np.ndarray
    faces: np.ndarray
    appearance: Appearance
    face_normals: bool = True
    """Shaded with face normals (as fitted with `Stage2Config.face_normals`)."""

    def _shade(self, K: np.ndarray, T_turntable_cam: np.ndarray, width: int, height: int):
        r = rasterize(transform_points(inv_T(T_turntable_cam), self.vertices), self.faces, K, width, height)
        mask = r.mask
        v = torch.as_tensor(self.vertices, dtype=torch.float32)
        f = torch.as_tensor(self.faces, dtype=torch.int64)
        fv = f[torch.as_tensor(r.face[mask], dtype=torch.int64)]
        bary = torch.as_tensor(r.bary[mask], dtype=torch.float32)
        R = torch.as_tensor(T_turntable_cam[:3, :3], dtype=torch.float32)
        tri = v[fv]
        if self.face_normals:
            n = F.normalize(torch.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=1), dim=1, eps=1e-12)
        else:
            n = F.normalize((_vertex_normals(v, f)[fv] * bary[..., None]).sum(1), dim=1)
        p = (tri * bary[..., None]).sum(1)
        d = F.normalize(p - torch.as_tensor(T_turntable_cam[:3, 3], dtype=torch.float32), dim=1)
        n_cam, d_cam = n @ R, d @ R
        r_cam = d_cam - 2 * (d_cam * n_cam).sum(1, keepdim=True) * n_cam
        return mask, fv, bary, n_cam, r_cam

    @torch.no_grad()
    def render_covered(self, K: np.ndarray, T_turntable_cam: np.ndarray, width: int, height: int
                       ) -> tuple[np.ndarray, np.ndarray]:
        """(H x W x 3 float image (0..1) of the fitted model in a view, black where the mesh is not; H x W bool
        where the mesh is)."""
        covered, fv, bary, n_cam, r_cam = self._shade(K, T_turntable_cam, width, height)
        image = np.zeros((height, width, 3), np.float32)
        image[covered] = self.appearance.colour(fv, bary, n_cam, r_cam)[0].clamp(0, 1).numpy()
        return image, covered

    def render(self, K: np.ndarray, T_turntable_cam: np.ndarray, width: int, height: int,
               mask: np.ndarray | None = None) -> np.ndarray:
        """H x W x 3 float image (0..1) of the fitted model in a view (the report's renderer signature)."""
        return self.render_covered(K, T_turntable_cam, width, height)[0]

    @torch.no_grad()
    def specular_images(self, views: Views) -> np.ndarray:
        """N x H x W x 3 float32 highlights (0..255 sRGB units) the model predicts in each view."""
        out = np.zeros(views.rgb.shape, np.float32)
        for i in range(len(views)):
            covered, fv, bary, _, r_cam = self._shade(views.K, views.T_turntable_cam[i], views.width, views.height)
            out[i][covered] = 255.0 * self.appearance.specular(fv, bary, r_cam).numpy()
        return out

    def diffuse_views(self, views: Views) -> Views:
        """The views with the fitted highlights subtracted from their photos (for baking the albedo)."""
        rgb = np.clip(np.rint(views.rgb.astype(np.float32) - self.specular_images(views)), 0, 255).astype(np.uint8)
        return Views(rgb, views.masks, views.K, views.T_turntable_cam, views.names, views.truth, views.placement)


class _Scene:
    """The training views as tensors, and per-view rendering of the current mesh."""

    def __init__(self, views: Views):
        self.views = views
        self.rgb = torch.as_tensor(views.rgb).float().div_(255.0)
        self.sdf = torch.stack([torch.as_tensor(signed_distance_px(m)).clamp(-SDF_CLAMP_PX, SDF_CLAMP_PX)
                                for m in views.masks])
        self.K = torch.as_tensor(views.K, dtype=torch.float32)
        self.R = torch.as_tensor(views.T_turntable_cam[:, :3, :3], dtype=torch.float32)
        self.c = torch.as_tensor(views.T_turntable_cam[:, :3, 3], dtype=torch.float32)
        self.Kinv = torch.linalg.inv(self.K)

    def raster(self, i: int, vertices: np.ndarray, faces: np.ndarray):
        v = self.views
        return rasterize(transform_points(inv_T(v.T_turntable_cam[i]), vertices), faces, v.K, v.width, v.height)

    def project(self, i: int, p: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        cam = (p - self.c[i]) @ self.R[i]
        uv = cam[:, :2] / cam[:, 2:] * self.K[[0, 1], [0, 1]] + self.K[:2, 2]
        return uv, cam[:, 2]

    def sample_sdf(self, i: int, uv: torch.Tensor) -> torch.Tensor:
        """Bilinear samples of view i's mask signed distance (pixels, positive inside) at pixel coordinates."""
        return _bilinear(self.sdf[i], uv)


def _initial_albedo(scene: _Scene, vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray,
                    tolerance_m: float) -> np.ndarray:
    """V x 3 mean photo colour (0..1) of each vertex over the views that see it frontally enough."""
    views = scene.views
    acc, wsum = np.zeros((len(vertices), 3)), np.zeros(len(vertices))
    for i in range(len(views)):
        r = scene.raster(i, vertices, faces)
        uv, z = views.project(i, vertices)
        px, ok = views.pixels(uv)
        ok[ok] &= np.abs(r.depth[px[ok, 1], px[ok, 0]] - z[ok]) < tolerance_m
        to_cam = views.T_turntable_cam[i][:3, 3] - vertices
        cos = np.einsum("nc,nc->n", normals, to_cam) / np.linalg.norm(to_cam, axis=1)
        ok &= cos > 0.3
        acc[ok] += cos[ok, None] * views.rgb[i][px[ok, 1], px[ok, 0]] / 255.0
        wsum[ok] += cos[ok]
    mean = acc.sum(0) / max(wsum.sum(), 1e-9)
    return np.where(wsum[:, None] > 0, acc / np.maximum(wsum, 1e-9)[:, None], mean)


def _intersect(o: torch.Tensor, d: torch.Tensor, tri: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Barycentrics (N x 3) and ray parameter of rays o + t d through triangles N x 3 x 3 (Moller-Trumbore)."""
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    p = torch.cross(d, e2, dim=1)
    det = (e1 * p).sum(1)
    s = o - tri[:, 0]
    q = torch.cross(s, e1, dim=1)
    b1, b2 = (s * p).sum(1) / det, (d * q).sum(1) / det
    return torch.stack([1 - b1 - b2, b1, b2], 1), (e2 * q).sum(1) / det


def _errors(scene: _Scene, vertices: np.ndarray, faces: np.ndarray, appearance: Appearance,
            face_normals: bool) -> dict:
    """Mean photometric error (0..255, over pixels both masks cover) and outline error (pixels: the area where
    rendered and photo masks disagree over the photo mask's outline length) over all views."""
    result = Stage2Result(vertices, faces, appearance, face_normals)
    photo, outline = [], []
    views = scene.views
    for i in range(len(views)):
        image, covered = result.render_covered(views.K, views.T_turntable_cam[i], views.width, views.height)
        both = covered & views.masks[i]
        photo.append(float(np.abs(255.0 * image[both] - views.rgb[i][both]).mean()) if both.any() else 0.0)
        sdf = scene.sdf[i].numpy()
        perimeter = max(int(((sdf > 0) & (sdf <= 0.5)).sum()), 1)
        outline.append(float((covered ^ views.masks[i]).sum()) / perimeter)
    return {"photometric": round(float(np.mean(photo)), 3), "outline_px": round(float(np.mean(outline)), 4)}


def refine_stage2(mesh: trimesh.Trimesh, views: Views, cfg: Stage2Config, progress: ProgressFn = no_progress,
                  fixed: np.ndarray | None = None) -> tuple[trimesh.Trimesh, Stage2Result, dict]:
    """The mesh (turntable frame) with its vertices moved by stage 2, the fitted model, and stats (photometric and
    outline error at the start and the end, time). `fixed` (V booleans): vertices that stay (the plate cut)."""
    start = time.monotonic()
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    scene = _Scene(views)
    pixel_m = views.pixel_m
    faces_np = np.asarray(mesh.faces, dtype=np.int64)
    v0 = torch.as_tensor(mesh.vertices, dtype=torch.float32)
    f = torch.as_tensor(faces_np)
    free = torch.ones(len(v0), 1) if fixed is None else torch.as_tensor(~fixed, dtype=torch.float32)[:, None]
    A = _laplacian(faces_np, len(v0))
    appearance = Appearance(_initial_albedo(scene, mesh.vertices, faces_np, mesh.vertex_normals,
                                            DEPTH_TOLERANCE_PX * pixel_m), cfg.lobes)
    before = _errors(scene, mesh.vertices, faces_np, appearance, cfg.face_normals)
    offsets = torch.nn.Parameter(torch.zeros_like(v0))
    step = cfg.step_px * pixel_m
    opt = torch.optim.Adam([{"params": [offsets], "lr": step},
                            {"params": list(appearance.parameters()), "lr": cfg.appearance_lr}])
    order: list[int] = []
    for it in range(cfg.iterations):
        if not order:
            order = list(rng.permutation(len(views)))
        i = order.pop()
        k = (it - cfg.warmup) / max(cfg.iterations - cfg.warmup - 1, 1)
        opt.param_groups[0]["lr"] = 0.0 if it < cfg.warmup else \
            step * (cfg.final_step + (1 - cfg.final_step) * 0.5 * (1 + np.cos(np.pi * k)))
        v = v0 + offsets * free
        v_np = v.detach().numpy().astype(np.float64)
        r = scene.raster(i, v_np, faces_np)
        loss = _photometric(scene, i, r, v, f, appearance, cfg, rng)
        loss = loss + cfg.silhouette * _outline(scene, i, r, v, f, pixel_m, cfg)
        u = offsets * free
        lap = (u - torch.sparse.mm(A, u)) / pixel_m
        loss = loss + cfg.smoothness * (lap * lap).sum(1).mean()
        loss = loss + cfg.specular_l1 * F.softplus(appearance.specular_logit).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if it % 10 == 0 or it == cfg.iterations - 1:
            progress(Progress((it + 1) / cfg.iterations, "stage2", message=f"step {it + 1}/{cfg.iterations}"))
    vertices = mesh.vertices + (offsets.detach() * free).numpy().astype(np.float64)
    after = _errors(scene, vertices, faces_np, appearance, cfg.face_normals)
    moved = np.linalg.norm(vertices - mesh.vertices, axis=1)
    stats = {"iterations": cfg.iterations, "before": before, "after": after,
             "median_move_mm": round(1000 * float(np.median(moved)), 3),
             "max_move_mm": round(1000 * float(moved.max(initial=0.0)), 3),
             "seconds": round(time.monotonic() - start, 2)}
    result = Stage2Result(vertices, faces_np, appearance, cfg.face_normals)
    return trimesh.Trimesh(vertices, faces_np, process=False), result, stats


def _photometric(scene: _Scene, i: int, r, v: torch.Tensor, f: torch.Tensor, appearance: Appearance,
                 cfg: Stage2Config, rng: np.random.Generator) -> torch.Tensor:
    """Huber error of the model's colour against view i's photo at sampled pixels both masks cover."""
    ys, xs = np.nonzero(r.mask & scene.views.masks[i])
    if not len(ys):
        return v.sum() * 0.0
    pick = rng.choice(len(ys), size=min(cfg.pixels, len(ys)), replace=False)
    ys, xs = ys[pick], xs[pick]
    fv = f[torch.as_tensor(r.face[ys, xs], dtype=torch.int64)]
    pix = torch.stack([torch.as_tensor(xs, dtype=torch.float32), torch.as_tensor(ys, dtype=torch.float32),
                       torch.ones(len(xs))], 1)
    d = F.normalize((pix @ scene.Kinv.T) @ scene.R[i].T, dim=1)
    o = scene.c[i].expand_as(d)
    tri = v[fv]
    bary, _ = _intersect(o, d, tri)
    if cfg.face_normals:
        n = F.normalize(torch.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=1), dim=1, eps=1e-12)
    else:
        n = F.normalize((_vertex_normals(v, f)[fv] * bary[..., None]).sum(1), dim=1)
    n_cam, d_cam = n @ scene.R[i], d @ scene.R[i]
    # Grazing faces give unstable intersections; they are the outline term's.
    ok = (n_cam * d_cam).sum(1).abs() > 0.1
    r_cam = d_cam - 2 * (d_cam * n_cam).sum(1, keepdim=True) * n_cam
    colour, _ = appearance.colour(fv[ok], bary[ok], n_cam[ok], r_cam[ok])
    observed = scene.rgb[i][torch.as_tensor(ys[ok.numpy()]), torch.as_tensor(xs[ok.numpy()])]
    return F.huber_loss(colour, observed, delta=cfg.huber, reduction="mean") / cfg.huber


def _outline(scene: _Scene, i: int, r, v: torch.Tensor, f: torch.Tensor, pixel_m: float,
             cfg: Stage2Config) -> torch.Tensor:
    """Mean squared difference (pixels) between the photo mask's and the rendered mask's signed distances at the
    vertices near view i's rendered outline: where the rendering's outline stands outside the photo's, its
    vertices are drawn in, and out where it stands inside. (Not "each rim vertex onto the photo outline": a plain
    face seen edge-on has all its vertices near the outline, and only the outermost belong on it.)"""
    rendered = torch.as_tensor(signed_distance_px(r.mask)).clamp(-SDF_CLAMP_PX, SDF_CLAMP_PX)
    with torch.no_grad():
        n = _vertex_normals(v, f)
        to_cam = F.normalize(scene.c[i] - v, dim=1)
        rim = (n * to_cam).sum(1).abs() < cfg.rim_cos
        uv, z = scene.project(i, v)
        px = uv.round().long()
        h, w = r.mask.shape
        inside = (px[:, 0] >= 0) & (px[:, 0] < w) & (px[:, 1] >= 0) & (px[:, 1] < h) & (z > 0) & rim
        k = torch.nonzero(inside)[:, 0]
        depth = torch.as_tensor(r.depth)[px[k, 1], px[k, 0]]
        front = ~torch.isfinite(depth) | (z[k] <= depth + DEPTH_TOLERANCE_PX * pixel_m)
        k = k[(rendered[px[k, 1], px[k, 0]].abs() <= 1.5) & front]
    if not len(k):
        return v.sum() * 0.0
    uv, _ = scene.project(i, v[k])
    target = _bilinear(rendered, uv.detach())
    return ((scene.sample_sdf(i, uv) - target) ** 2).mean()


def _bilinear(image: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of an H x W image at N x 2 pixel coordinates (border clamped)."""
    h, w = image.shape
    grid = torch.stack([(uv[:, 0] + 0.5) / w * 2 - 1, (uv[:, 1] + 0.5) / h * 2 - 1], -1)
    return F.grid_sample(image[None, None], grid[None, None], mode="bilinear", padding_mode="border",
                         align_corners=False)[0, 0, 0]
