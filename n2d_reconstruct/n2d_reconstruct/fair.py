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
vertices here: at a 45 degree camera elevation a rounded dome touches the outlines too, to within a pixel.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy import sparse
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import spsolve

from n2d_common.progress import Progress, ProgressFn, no_progress
from n2d_reconstruct.data import Views
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

    def __post_init__(self):
        if not self.min_contrast >= 0:
            raise ValueError(f"fair.min_contrast must be >= 0, got {self.min_contrast}")
        if self.views < 1 or self.patch_size < 2:
            raise ValueError("fair.views must be >= 1 and fair.patch_size >= 2")


def patch_contrast(mesh: trimesh.Trimesh, views: Views, cfg: FairConfig) -> np.ndarray:
    """Per vertex, the median over its `cfg.views` most frontal views of the grey-level standard deviation of a
    patch around it (0..255); infinite where no view sees it."""
    v, n = mesh.vertices, mesh.vertex_normals
    pixel_m = float(np.median(np.linalg.norm(views.T_turntable_cam[:, :3, 3], axis=1))) / views.K[0, 0]
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


def fair_plain(mesh: trimesh.Trimesh, views: Views, cfg: FairConfig, fixed: np.ndarray | None = None,
               progress: ProgressFn = no_progress) -> tuple[trimesh.Trimesh, dict | None]:
    """`mesh` with its plain vertices spanned by a membrane (`fixed` ones stay), and what moved."""
    if not cfg.enabled:
        return mesh, None
    progress(Progress(0.0, "fair", message="patch contrast in the most frontal views"))
    plain = patch_contrast(mesh, views, cfg) < cfg.min_contrast
    if fixed is not None:
        plain &= ~fixed
    out = span(mesh, plain)
    moved = np.linalg.norm(out.vertices - mesh.vertices, axis=1)
    return out, {"plain_fraction": round(float(plain.mean()), 4), "max_move_mm": round(float(moved.max()) * 1000, 3),
                 "mean_move_mm": round(float(moved[plain].mean()) * 1000 if plain.any() else 0.0, 3)}
