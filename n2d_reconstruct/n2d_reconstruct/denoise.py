"""Feature-preserving mesh denoising: bilateral filtering of the face normals, then vertices fitted to them.

Bilateral normal filtering (Zheng et al. 2011): each face normal becomes the mean of the normals of the faces
near it, weighted by their area, a Gaussian of the distance between centroids (sigma: the mean neighbour
distance) and a Gaussian of the normals' difference (`sigma_r`). Ripples on a flat or gently curved patch
average out; the two sides of an edge or corner, whose normals differ by more than `sigma_r`, do not mix.
The vertices then follow the filtered normals (Sun et al. 2007): each moves by the mean, over its faces, of
the normal component of (face centroid - vertex), which flattens a face's ripple onto its mean plane rather
than shrinking it like Laplacian smoothing. Both reconstructions ripple by a few tenths of a millimetre on
surfaces that are flat in truth, and the bounding box is made of the ripple's crests.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy import sparse

from n2d_common.progress import Progress, ProgressFn, no_progress


@dataclass
class DenoiseConfig:
    """Bilateral normal filtering of the reconstructed mesh."""

    iterations: int = 100
    """Normal filtering iterations (0: no denoising)."""
    sigma_r: float = 0.25
    """Width of the Gaussian over normal differences |n_i - n_j| (0.25: about 14 degrees)."""
    rings: int = 2
    """Faces within this many vertex rings of a face are its neighbours."""
    vertex_iterations: int = 60
    """Iterations fitting the vertices to the filtered normals."""

    def __post_init__(self):
        if self.iterations < 0 or self.vertex_iterations < 0 or self.rings < 1 or self.sigma_r <= 0:
            raise ValueError("denoise needs iterations, vertex_iterations >= 0, rings >= 1 and sigma_r > 0")


def face_neighbours(faces: np.ndarray, n_vertices: int, rings: int) -> tuple[np.ndarray, np.ndarray]:
    """Pairs (i, j) of faces within `rings` vertex rings of each other (each face is its own neighbour)."""
    f = len(faces)
    incidence = sparse.csr_matrix((np.ones(3 * f), (np.repeat(np.arange(f), 3), faces.ravel())), shape=(f, n_vertices))
    near = (incidence @ incidence.T).tocsr()
    for _ in range(rings - 1):
        near = (near @ near).tocsr()
    near = near.tocoo()
    return near.row, near.col


def _face_geometry(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centroids, unit normals and areas of the faces."""
    corners = vertices[faces]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    norm = np.linalg.norm(cross, axis=1)
    return corners.mean(axis=1), cross / np.maximum(norm, 1e-30)[:, None], 0.5 * norm


def filter_normals(vertices: np.ndarray, faces: np.ndarray, cfg: DenoiseConfig) -> np.ndarray:
    """The bilaterally filtered unit face normals (F x 3)."""
    i, j = face_neighbours(faces, len(vertices), cfg.rings)
    centroids, normals, areas = _face_geometry(vertices, faces)
    distance2 = np.sum((centroids[i] - centroids[j]) ** 2, axis=1)
    sigma_s = np.mean(np.sqrt(distance2[i != j]))
    spatial = areas[j] * np.exp(-distance2 / (2.0 * sigma_s**2))
    for _ in range(cfg.iterations):
        weight = spatial * np.exp(-np.sum((normals[i] - normals[j]) ** 2, axis=1) / (2.0 * cfg.sigma_r**2))
        summed = sparse.csr_matrix((weight, (i, j)), shape=(len(faces), len(faces))) @ normals
        length = np.linalg.norm(summed, axis=1, keepdims=True)
        normals = np.where(length > 0, summed / np.maximum(length, 1e-30), normals)  # degenerate patches keep theirs
    return normals


def fit_vertices(vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray, iterations: int,
                 fixed: np.ndarray | None = None) -> np.ndarray:
    """Vertices moved so that their faces lie across `normals` (fixed vertices stay)."""
    vertices = vertices.copy()
    n = len(vertices)
    valence = np.bincount(faces.ravel(), minlength=n)[:, None]
    free = np.ones(n, dtype=bool) if fixed is None else ~fixed
    for _ in range(iterations):
        corners = vertices[faces]
        centroids = corners.mean(axis=1)
        move = np.zeros_like(vertices)
        for k in range(3):
            along = np.sum(normals * (centroids - corners[:, k]), axis=1, keepdims=True) * normals
            for axis in range(3):
                move[:, axis] += np.bincount(faces[:, k], weights=along[:, axis], minlength=n)
        vertices[free] += move[free] / valence[free]
    return vertices


def denoise(mesh: trimesh.Trimesh, cfg: DenoiseConfig, fixed: np.ndarray | None = None,
            progress: ProgressFn = no_progress) -> trimesh.Trimesh:
    """The mesh with its normals bilaterally filtered and its vertices fitted to them (same faces)."""
    if cfg.iterations == 0:
        return mesh
    progress(Progress(0.0, "denoise", message="filtering normals"))
    normals = filter_normals(mesh.vertices, mesh.faces, cfg)
    progress(Progress(0.5, "denoise", message="fitting vertices"))
    vertices = fit_vertices(mesh.vertices, mesh.faces, normals, cfg.vertex_iterations, fixed)
    return trimesh.Trimesh(vertices, mesh.faces, process=False)
