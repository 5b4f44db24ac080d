"""Photo-consistency refinement of the visual hull: move each vertex inward to where the photos agree.

A visual hull is the largest shape consistent with the silhouettes; from one ring of views it keeps
a "roof" over the top of an object and slabs over faces seen only obliquely. The true surface lies
inside it. For every vertex, a small patch tangent to the surface is swept inward along the normal;
at each depth the patch is projected into the views that see the vertex most frontally, and the
normalised cross-correlation (NCC) of its grey values with the reference (most frontal) view is
averaged. The depth with the best score wins where the score is high and the patch textured.

The found depths become displacement vectors (inward along each normal), and a robust membrane fitted
to them moves every vertex: unfound vertices are interpolated, single bad matches damped. Fitting
vectors, not depths along the normals, lets a roof's tilted sides settle onto the flat top under them.
Where nothing was found (a plain top under a roof's ridge), interpolated displacements leave a crest,
since the ridge had further to go than its sides; there a bending term flattens the moved surface
itself (`flatten`). The silhouettes bound the search: each ray that grazes a mask's outline touches
the object, so one hull vertex on it is held (`silhouette_anchors`); glossy objects, whose reflections
match at depths inside a convex surface, keep their outline. docs/experiments.md has the measurements.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import trimesh
from scipy import sparse
from scipy.sparse.linalg import spsolve
from scipy.spatial import cKDTree

from n2d_common.frames import inv_T
from n2d_common.progress import Progress, ProgressFn, no_progress
from n2d_common.raster import render_depth
from n2d_reconstruct.data import Views
from n2d_reconstruct.hull import signed_distance_px

FIXED_WEIGHT = 1000.0
"""Weight of a vertex known to be on the surface in the membrane fit (a found depth weighs at most 1)."""


@dataclass
class RefineConfig:
    """Photo-consistency refinement of the hull (fast path)."""

    enabled: bool = True
    """Refine the hull (false: the plain visual hull)."""
    min_faces: int = 40000
    """The refinement works on a mesh of up to this many faces, or as many as marching cubes gives if fewer, and
    the result is decimated to `mesh.target_faces` after it: a coarse mesh cannot follow the depths found (box,
    36 views of 320x240, 2000 faces: Chamfer 1.17 mm for the hull, 1.55 refined coarse, 0.60 refined fine)."""
    passes: int = 3
    """Searches in a row, each from the surface (normals, visibility) the previous one left: each pass starts
    closer, so finds more of the surface (docs/experiments.md)."""
    max_depth_m: float = 0.03
    """How far inside the hull the surface is searched, metres."""
    outward_m: float = 0.002
    """How far outside the hull it is searched (mask boundaries are not exact), metres."""
    step_px: float = 0.6
    """Depth step of the search, in pixels on the object (the size of a pixel at the object's distance)."""
    patch_size: int = 7
    """Patch samples per side, one pixel on the object apart."""
    views_per_vertex: int = 7
    """Most frontal views compared per vertex (the first is the reference)."""
    min_separation_deg: float = 5.0
    """Views compared for a vertex are at least this far apart as seen from it: a denser ring then gives the same
    baselines, not shorter ones that blur the NCC's peak over depth (5 keeps all neighbours in a 36-view ring at
    45 degrees elevation, 7 degrees apart, and every other one of 72)."""
    min_cos: float = 0.4
    """Views that see the surface more obliquely than this cosine are not used."""
    min_ncc: float = 0.5
    """A vertex moves only where the best mean NCC reaches this."""
    min_contrast: float = 6.0
    """A vertex moves only where its reference patch has this much grey-level standard deviation (0..255;
    the sensor noise alone gives about 3)."""
    min_prominence: float = 0.2
    """A vertex moves only where the best NCC exceeds the median NCC over the searched depths by this much
    (flat or self-similar texture matches at every depth)."""
    agree_steps: int = 2
    """A view agrees with the chosen depth when its own best depth is within this many steps."""
    min_agreeing_views: int = 4
    """A vertex moves only where this many of the compared views (besides the reference) agree."""
    smoothness: float = 4.0
    """Weight of the membrane term that spreads found displacements to their neighbours and smooths them."""
    flatten: float = 100.0
    """Weight of the bending term on vertices without a found depth: each is drawn to the mean of its neighbours'
    moved positions, so a plain patch comes out flat or evenly curved like the surface around it, and a hull's
    ridge over a plain top comes down with the top (0: unfound displacements are only interpolated)."""
    robust_m: float = 0.0015
    """Found displacements further than this from the fitted ones are down-weighted (Huber), metres."""
    smooth_iterations: int = 5
    """Taubin smoothing iterations after the vertices moved."""
    keep_silhouettes: bool = True
    """Hold one hull vertex on every ray that grazes a mask's outline (see `silhouette_anchors`)."""
    silhouette_radius_px: float = 1.0
    """Hull vertices projecting within this many pixels of an outline pixel lie on its ray."""

    def __post_init__(self):
        if self.passes < 1 or self.min_faces < 0:
            raise ValueError("passes must be >= 1 and min_faces >= 0")
        if self.step_px <= 0 or self.max_depth_m <= 0:
            raise ValueError("step_px and max_depth_m must be > 0")
        if self.views_per_vertex < 2 or self.patch_size < 3:
            raise ValueError("views_per_vertex must be >= 2 and patch_size >= 3")
        if not 0 <= self.min_separation_deg < 90:
            raise ValueError("min_separation_deg must be in [0, 90)")
        if self.silhouette_radius_px <= 0:
            raise ValueError("silhouette_radius_px must be > 0")
        if self.smoothness < 0 or self.flatten < 0:
            raise ValueError("smoothness and flatten must be >= 0")


def refine_surface(mesh: trimesh.Trimesh, views: Views, cfg: RefineConfig, progress: ProgressFn = no_progress,
                   fixed: np.ndarray | None = None) -> tuple[trimesh.Trimesh, dict]:
    """The hull `mesh` (turntable frame) with its vertices moved to the photo-consistent depth, and stats.
    `fixed` (N booleans) marks vertices known to be on the surface already (the cut on the plate): they stay, and
    hold their neighbours, which no view may see either."""
    v = mesh.vertices
    n = mesh.vertex_normals
    grey = grey_images(views)
    pixel_m = views.pixel_m
    step = cfg.step_px * pixel_m
    cos, visible = visibility(mesh, views, cfg.min_cos, 2 * step + 0.001)
    order, usable = pick_views(v, views.T_turntable_cam[:, :3, 3], cos, visible, cfg)
    depths = np.arange(-cfg.outward_m, cfg.max_depth_m + 1e-12, step)
    found = np.full(len(v), np.nan)
    idx = np.flatnonzero(usable)
    chunk = 512
    for s in range(0, len(idx), chunk):
        part = idx[s:s + chunk]
        found[part] = _search(v[part], n[part], order[part], depths, pixel_m, views, grey, cfg)
        progress(Progress(min(1.0, (s + chunk) / max(len(idx), 1)), "refining",
                          message=f"{min(s + chunk, len(idx))}/{len(idx)} vertices"))
    target = np.where(np.isfinite(found)[:, None], -found[:, None] * n, np.nan)
    held = np.zeros(len(v), bool) if fixed is None else fixed.copy()
    u = smooth_displacements(mesh, target, cfg, held)
    if cfg.keep_silhouettes:
        held |= silhouette_anchors(v, -np.einsum("nc,nc->n", u, n), views, cfg.silhouette_radius_px)
        u = smooth_displacements(mesh, target, cfg, held)
    out = trimesh.Trimesh(v + u, mesh.faces, process=False)
    d = -np.einsum("nc,nc->n", u, n)
    stats = {"vertices": len(v), "searched": int(usable.sum()), "moved": int(np.isfinite(found).sum()),
             "median_depth_mm": round(1000 * float(np.median(d[np.isfinite(found)])) if np.isfinite(found).any()
                                      else 0.0, 3),
             "max_depth_mm": round(1000 * float(d.max()), 3),
             "silhouette_anchors": int(held.sum() - (0 if fixed is None else fixed.sum()))}
    return out, stats


def smooth_displacements(mesh: trimesh.Trimesh, found: np.ndarray, cfg: RefineConfig,
                         fixed: np.ndarray | None = None, rounds: int = 3) -> np.ndarray:
    """N x 3 vertex displacements u minimising

        sum_found w |u - found|^2 + smoothness * sum_edges |u_i - u_j|^2 + flatten * sum_free |B(v + u)_i|^2,

    with Huber weights w re-estimated over `rounds` (a robust membrane fit: vertices without a found
    displacement, NaN rows of `found`, are interpolated). B(x)_i = x_i - mean of its neighbours is the umbrella
    operator; on the free vertices (neither found nor fixed) it bends the moved surface flat. `fixed` vertices
    are held in place by a weight no Huber step lowers."""
    n = len(mesh.vertices)
    edges = mesh.edges_unique
    adjacency = sparse.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    adjacency = (adjacency + adjacency.T).tocsr()
    degree = np.asarray(adjacency.sum(1)).ravel()
    laplacian = sparse.diags(degree) - adjacency
    fixed = np.zeros(n, bool) if fixed is None else fixed
    has = np.isfinite(found).all(1) & ~fixed
    free = ~has & ~fixed
    umbrella = sparse.diags(free / np.maximum(degree, 1)) @ laplacian
    bending = cfg.flatten * (umbrella.T @ umbrella)
    pull = -(bending @ mesh.vertices)
    target = np.where(has[:, None], found, 0.0)
    weight = has.astype(float)
    u = target
    for _ in range(rounds):
        A = sparse.diags(weight + FIXED_WEIGHT * fixed + 1e-6) + cfg.smoothness * laplacian + bending
        u = spsolve(A.tocsc(), weight[:, None] * target + pull)
        residual = np.linalg.norm(u - target, axis=1)
        weight = np.where(has, np.minimum(1.0, cfg.robust_m / np.maximum(residual, 1e-12)), 0.0)
    return u


def silhouette_anchors(before: np.ndarray, depth: np.ndarray, views: Views,
                       radius_px: float) -> np.ndarray:
    """Vertices to hold on the hull so that the surface keeps every view's silhouette.

    Each pixel on a mask's outline sees a ray that touches the object. Hull vertices projecting within
    `radius_px` of it lie along that ray (on the hull's surface there); the one that moved least
    (smallest `depth`) is held. A roof over a flat top lies on the same ray as the top's edge, which
    moved least, so the roof stays free."""
    held = np.zeros(len(before), dtype=bool)
    for i in range(len(views)):
        uv, _ = views.project(i, before)
        dist = signed_distance_px(views.masks[i])
        px = np.clip(np.rint(uv).astype(int), 0, [views.width - 1, views.height - 1])
        k = np.flatnonzero(np.abs(dist[px[:, 1], px[:, 0]]) <= radius_px + 0.5)
        outline = np.argwhere((dist > 0) & (dist <= 0.5))[:, ::-1].astype(float)
        if not len(k) or not len(outline):
            continue
        _, near = cKDTree(uv[k]).query(outline, k=min(64, len(k)), distance_upper_bound=radius_px)
        near = near.reshape(len(outline), -1)
        cost = np.where(near < len(k), depth[k][np.minimum(near, len(k) - 1)], np.inf)
        best = cost.argmin(1)
        hit = np.isfinite(cost[np.arange(len(outline)), best])
        held[k[near[np.arange(len(outline)), best][hit]]] = True
    return held


def visibility(mesh: trimesh.Trimesh, views: Views, min_cos: float,
               tolerance_m: float) -> tuple[np.ndarray, np.ndarray]:
    """V x N cosine between each vertex normal and the direction to each camera, and whether it is seen: not
    hidden (its depth within `tolerance_m` of the mesh's depth there) and no more oblique than `min_cos`."""
    v, n = mesh.vertices, mesh.vertex_normals
    cos = np.zeros((len(v), len(views)))
    visible = np.zeros((len(v), len(views)), dtype=bool)
    for i in range(len(views)):
        depth = render_depth(v, mesh.faces, views.K, inv_T(views.T_turntable_cam[i]), views.width, views.height)
        uv, z = views.project(i, v)
        px, inside = views.pixels(uv)
        seen = np.zeros(len(v), dtype=bool)
        seen[inside] = np.abs(depth[px[inside, 1], px[inside, 0]] - z[inside]) < tolerance_m
        to_cam = views.T_turntable_cam[i][:3, 3] - v
        cos[:, i] = np.einsum("nc,nc->n", n, to_cam) / np.linalg.norm(to_cam, axis=1)
        visible[:, i] = seen & (cos[:, i] > min_cos)
    return cos, visible


def pick_views(v: np.ndarray, eyes: np.ndarray, cos: np.ndarray, visible: np.ndarray,
               cfg: RefineConfig) -> tuple[np.ndarray, np.ndarray]:
    """The views compared for each vertex: V x views_per_vertex indices into the N camera centres `eyes`, the
    highest `cos` (V x N) first, each visible and at least min_separation_deg from those before it as seen from
    the vertex; and whether a vertex got all of them."""
    to_cam = eyes[None] - v[:, None]
    to_cam /= np.linalg.norm(to_cam, axis=2, keepdims=True)
    score = np.where(visible, cos, -np.inf)
    order = np.zeros((len(v), cfg.views_per_vertex), dtype=int)
    found = np.ones(len(v), dtype=bool)
    rows = np.arange(len(v))
    limit = np.cos(np.radians(cfg.min_separation_deg))
    for k in range(cfg.views_per_vertex):
        order[:, k] = score.argmax(1)
        found &= np.isfinite(score[rows, order[:, k]])
        score[np.einsum("vnc,vc->vn", to_cam, to_cam[rows, order[:, k]]) > limit] = -np.inf
        score[rows, order[:, k]] = -np.inf  # at 0 degrees the rounded self-product may not exceed cos(0)
    return order, found


def tangent_patch(n: np.ndarray, size: int, spacing: float) -> np.ndarray:
    """V x size^2 x 3 offsets of a square grid of samples `spacing` apart in the plane perpendicular to each unit
    normal, centred on zero."""
    helper = np.where(np.abs(n[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    c = (np.arange(size) - (size - 1) / 2) * spacing
    a, b = np.meshgrid(c, c, indexing="ij")
    return a.reshape(1, -1, 1) * t1[:, None] + b.reshape(1, -1, 1) * t2[:, None]


def grey_images(views: Views) -> torch.Tensor:
    """N x 1 x H x W float grey values (0..255) of the views."""
    return torch.as_tensor(views.rgb.astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32))[:, None]


def sample_view(grey: torch.Tensor, views: Views, view: int, points: np.ndarray) -> np.ndarray:
    """Grey values (bilinear) where N x 3 turntable-frame `points` project into view `view`."""
    uv, _ = views.project(view, points)
    grid = torch.as_tensor(2 * uv / [views.width - 1, views.height - 1] - 1, dtype=torch.float32).view(1, -1, 1, 2)
    values = torch.nn.functional.grid_sample(grey[view:view + 1], grid, align_corners=True, padding_mode="border")
    return values.view(-1).numpy()


def _search(v, n, order, depths, spacing: float, views: Views, grey: torch.Tensor, cfg: RefineConfig) -> np.ndarray:
    """Best inward depth of each vertex (NaN where no depth is trustworthy); patch samples `spacing` apart."""
    patch = tangent_patch(n, cfg.patch_size, spacing)                                         # V x P x 3
    points = v[:, None, None] - depths[None, :, None, None] * n[:, None, None] + patch[:, None]  # V x D x P x 3
    samples = np.zeros((len(v), order.shape[1]) + points.shape[1:3], np.float32)              # V x M x D x P
    for j in np.unique(order):
        rows, slots = np.nonzero(order == j)
        samples[rows, slots] = sample_view(grey, views, j, points[rows].reshape(-1, 3)).reshape(len(rows),
                                                                                               *points.shape[1:3])
    centred = samples - samples.mean(-1, keepdims=True)
    std = np.sqrt((centred ** 2).mean(-1))                                                   # V x M x D
    unit = centred / np.maximum(std, 1e-3)[..., None]
    pair = (unit[:, :1] * unit[:, 1:]).mean(-1)                                               # V x M-1 x D
    ncc = pair.mean(1)                                                                        # V x D
    best = ncc.argmax(1)
    # agreement: most views must peak near the same depth on their own (repetitive texture fools one view)
    agree = (np.abs(pair.argmax(-1) - best[:, None]) <= cfg.agree_steps).sum(1) >= cfg.min_agreeing_views
    score = ncc[np.arange(len(v)), best]
    # sub-step position of the peak from a parabola through it and its neighbours
    lo, hi = np.clip(best - 1, 0, len(depths) - 1), np.clip(best + 1, 0, len(depths) - 1)
    y0, y1, y2 = ncc[np.arange(len(v)), lo], score, ncc[np.arange(len(v)), hi]
    curvature = y0 - 2 * y1 + y2
    shift = np.where((curvature < 0) & (lo < best) & (hi > best), 0.5 * (y0 - y2) / np.minimum(curvature, -1e-9), 0.0)
    depth = depths[best] + np.clip(shift, -0.5, 0.5) * (depths[1] - depths[0])
    prominent = score - np.median(ncc, axis=1) >= cfg.min_prominence
    ok = agree & prominent & (score >= cfg.min_ncc) & (std[np.arange(len(v)), 0, best] >= cfg.min_contrast)
    return np.where(ok, depth, np.nan)
