"""Plain surfaces spanned taut: where no view shows texture, the surface becomes the membrane across its rim.

NeuS places a surface where the photos agree on it. A patch that shows no texture (a plain top, a plain
flank) agrees with the photos at any depth the silhouettes allow, so it keeps the shape training started
from: the visual hull's roof, rounded (converged NeuS: a bottle's flat, plain cap top comes out as a dome
6.7 mm high; a box's plain top has bumps of 1-3 mm). Nothing in the photos prefers one of those surfaces, so
the tautest is taken: each plain vertex moves to the mean of its neighbours (a discrete membrane, the
harmonic fill between the textured vertices, solved at once). It spans a flat top by the plane through its
rim, and stays between the textured surfaces around it; the hull phase after it keeps it inside the
silhouettes. A vertex is plain when the grey level of a small patch around it, in its most frontal views,
varies less than `min_contrast` (sensor noise alone gives about 3 of 255). The silhouettes do not hold
vertices in advance (at a 45 degree camera elevation a rounded dome touches the outlines too, to within a
pixel, and would be kept) but check the result: where the spanned mesh no longer covers mask pixels that
the mesh covered before (a plain, curved flank pulled taut between a printed band and the plate cuts into
the silhouettes), the plain vertices seen there are held and the membrane solved again.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import trimesh
from scipy import sparse
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import spsolve

from n2d_common.frames import inv_T
from n2d_common.progress import Progress, ProgressFn, no_progress
from n2d_common.raster import render_depth
from n2d_reconstruct.data import Views
from n2d_reconstruct.hull import signed_distance_px
from n2d_reconstruct.refine import grey_images, sample_view, tangent_patch, visibility


@dataclass
class FairConfig:
    """The membrane over plain surfaces (NeuS)."""

    enabled: bool = True
    """Span plain surfaces (false: keep NeuS's surface as it is)."""
    min_contrast: float = 5.0
    """A vertex is plain when its patch's grey-level standard deviation (0..255), the median over its most frontal
    views, is below this (converged NeuS, 3 / 5: box z +0.78 / +0.57 %, bottle z +0.56 / +0.36 %)."""
    views: int = 3
    """Most frontal views whose patch contrast is compared."""
    patch_size: int = 7
    """Patch samples per side, one pixel on the object apart."""
    min_cos: float = 0.4
    """Views that see the surface more obliquely than this cosine are not used."""
    silhouette_margin_px: float = 1.0
    """Mask pixels further inside the outline than this that the spanned mesh leaves uncovered hold the plain
    vertices seen there."""
    silhouette_rounds: int = 4
    """Times the membrane is solved again with the vertices so held."""

    def __post_init__(self):
        if not self.min_contrast >= 0:
            raise ValueError(f"fair.min_contrast must be >= 0, got {self.min_contrast}")
        if self.views < 1 or self.patch_size < 2:
            raise ValueError("fair.views must be >= 1 and fair.patch_size >= 2")
        if self.silhouette_rounds < 0 or not self.silhouette_margin_px >= 0:
            raise ValueError("fair.silhouette_rounds and fair.silhouette_margin_px must be >= 0")


def patch_contrast(mesh: trimesh.Trimesh, views: Views, cfg: FairConfig) -> np.ndarray:
    """Per vertex, the median over its `cfg.views` most frontal views of the grey-level standard deviation of a
    patch around it (0..255); infinite where no view sees it."""
    v, n = mesh.vertices, mesh.vertex_normals
    pixel_m = views.pixel_m
    cos, visible = visibility(mesh, views, cfg.min_cos, 2 * pixel_m + 0.001)
    score = np.where(visible, cos, -np.inf)
    order = np.argsort(-score, axis=1)[:, :cfg.views]
    points = v[:, None] + tangent_patch(n, cfg.patch_size, pixel_m)
    grey = grey_images(views)
    std = np.full(order.shape, np.nan)
    for k in range(order.shape[1]):
        seen = np.isfinite(score[np.arange(len(v)), order[:, k]])
        for j in np.unique(order[seen, k]):
            rows = np.flatnonzero(seen & (order[:, k] == j))
            std[rows, k] = sample_view(grey, views, j, points[rows].reshape(-1, 3)).reshape(len(rows), -1).std(1)
    seen_any = np.isfinite(std).any(1)
    contrast = np.full(len(v), np.inf)
    contrast[seen_any] = np.nanmedian(std[seen_any], axis=1)
    return contrast


def span(mesh: trimesh.Trimesh, free: np.ndarray) -> trimesh.Trimesh:
    """`mesh` with each `free` vertex at the mean of its neighbours (the harmonic fill between the others). A
    group of free vertices with no other vertex next to it has no rim to span and stays."""
    if not free.any():
        return mesh
    n = len(mesh.vertices)
    edges = mesh.edges_unique
    adjacency = sparse.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    adjacency = (adjacency + adjacency.T).tocsr()
    free = free.copy()
    _, label = connected_components(adjacency[free][:, free], directed=False)
    rimmed = np.bincount(label, weights=(adjacency[free][:, ~free].sum(1).A1 > 0), minlength=label.max() + 1) > 0
    free[np.flatnonzero(free)[~rimmed[label]]] = False
    if not free.any():
        return mesh
    laplacian = (sparse.diags(np.asarray(adjacency.sum(1)).ravel()) - adjacency).tocsr()
    rhs = -(laplacian[free][:, ~free] @ mesh.vertices[~free])
    vertices = mesh.vertices.copy()
    vertices[free] = spsolve(laplacian[free][:, free].tocsc(), rhs)
    return trimesh.Trimesh(vertices, mesh.faces, process=False)


def covered(mesh: trimesh.Trimesh, views: Views, margin_px: float | None = None) -> np.ndarray:
    """N x H x W: the pixels of each view that the mesh covers (with `margin_px`: only those of them more than
    that inside the mask's outline)."""
    out = np.zeros(views.masks.shape, dtype=bool)
    for i in range(len(views)):
        T_cam = inv_T(views.T_turntable_cam[i])
        out[i] = np.isfinite(render_depth(mesh.vertices, mesh.faces, views.K, T_cam, views.width, views.height))
        if margin_px is not None:
            out[i] &= signed_distance_px(views.masks[i]) > margin_px
    return out


def uncovering(before: trimesh.Trimesh, inside: np.ndarray, after: trimesh.Trimesh, views: Views,
               candidates: np.ndarray) -> np.ndarray:
    """Which `candidates` (vertices of `before`) project onto pixels of `inside` (`covered(before, views,
    margin)`) that `after` (the same faces, moved) leaves uncovered."""
    held = np.zeros(len(before.vertices), dtype=bool)
    lost = inside & ~covered(after, views)
    for i in np.flatnonzero(lost.any(axis=(1, 2))):
        px, inside = views.pixels(views.project(i, before.vertices)[0])
        seen = inside & candidates
        near = cv2.dilate(lost[i].astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        held[seen] |= near[px[seen, 1], px[seen, 0]]
    return held


def fair_plain(mesh: trimesh.Trimesh, views: Views, cfg: FairConfig, fixed: np.ndarray | None = None,
               progress: ProgressFn = no_progress) -> tuple[trimesh.Trimesh, dict | None]:
    """`mesh` with its plain vertices spanned by a membrane (`fixed` ones stay) that keeps the silhouettes the
    mesh covered, and what moved."""
    if not cfg.enabled:
        return mesh, None
    progress(Progress(0.0, "fair", message="patch contrast in the most frontal views"))
    plain = patch_contrast(mesh, views, cfg) < cfg.min_contrast
    if fixed is not None:
        plain &= ~fixed
    free = plain.copy()
    out = span(mesh, free)
    inside = covered(mesh, views, cfg.silhouette_margin_px) if cfg.silhouette_rounds else None
    for _ in range(cfg.silhouette_rounds):
        held = uncovering(mesh, inside, out, views, free)
        if not held.any():
            break
        free &= ~held
        out = span(mesh, free)
    moved = np.linalg.norm(out.vertices - mesh.vertices, axis=1)
    return out, {"plain_fraction": round(float(plain.mean()), 4),
                 "held_by_silhouettes": round(float((plain & ~free).mean()), 4),
                 "max_move_mm": round(float(moved.max()) * 1000, 3),
                 "mean_move_mm": round(float(moved[free].mean()) * 1000 if free.any() else 0.0, 3)}
