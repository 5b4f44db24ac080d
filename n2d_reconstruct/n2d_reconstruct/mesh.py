"""Surface extraction from any signed distance field, and the mesh clean-up every method shares.

`extract_mesh` finds the object in a search box on a coarse grid, evaluates the field exactly only
in a narrow band around the surface on the fine grid (elsewhere the coarse values, trilinearly
upsampled, carry the sign), runs marching cubes, keeps the largest component, smooths with Taubin's
filter (which does not shrink), decimates to a face budget, removes pinched edges and
closes holes. Fields map N x 3 turntable-frame points (metres) to signed distances, negative inside.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass

import fast_simplification
import numpy as np
import torch
import trimesh
from scipy import ndimage
from skimage import measure

from n2d_common.errors import N2DError
from n2d_common.progress import Progress, ProgressFn, no_progress

Field = Callable[[np.ndarray], np.ndarray]
"""N x 3 points (metres) -> N signed distances (metres, negative inside)."""


@dataclass
class MeshConfig:
    """Marching cubes and clean-up."""

    voxel_m: float = 0.001
    """Fine grid spacing for marching cubes, metres."""
    coarse_factor: int = 4
    """The coarse grid (object search, narrow band) is this many fine voxels apart."""
    locate_voxel_m: float = 0.004
    """Grid spacing of the search for the object in the whole search box, metres."""
    smooth_iterations: int = 10
    """Taubin smoothing iterations (0: none)."""
    target_faces: int = 40000
    """Decimate to at most this many triangles (0: keep all)."""

    def __post_init__(self):
        if self.voxel_m <= 0 or self.locate_voxel_m <= 0:
            raise ValueError("voxel sizes must be > 0")
        if self.coarse_factor < 1:
            raise ValueError("coarse_factor must be >= 1")
        if self.smooth_iterations < 0 or self.target_faces < 0:
            raise ValueError("smooth_iterations and target_faces must be >= 0")


def _grid(box: np.ndarray, step: float) -> tuple[np.ndarray, tuple[int, int, int]]:
    """Nodes of a grid from box[0] with spacing `step` covering `box`: (points, shape)."""
    n = np.maximum(np.ceil((box[1] - box[0]) / step).astype(int), 1) + 1
    axes = [box[0, i] + step * np.arange(n[i]) for i in range(3)]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    return pts, tuple(int(x) for x in n)


def locate(field: Field, search_box: np.ndarray, step: float) -> np.ndarray:
    """2 x 3 box around the region where `field` is negative, with a margin of two grid steps."""
    pts, shape = _grid(search_box, step)
    inside = (field(pts) < 0).reshape(shape)
    if not inside.any():
        raise N2DError("the reconstruction is empty: no point of the search region is inside the object",
                       "check that the masks show the object and that the camera poses are right "
                       "(contact_sheet.png of the capture session)")
    idx = np.argwhere(inside)
    lo = search_box[0] + step * (idx.min(0) - 2)
    hi = search_box[0] + step * (idx.max(0) + 2)
    return np.stack([lo, hi])


def sample_narrow_band(field: Field, box: np.ndarray, voxel: float, factor: int,
                       progress: ProgressFn = no_progress) -> np.ndarray:
    """Field values on the fine grid over `box` (spacing `voxel`), exact within a band around the surface."""
    coarse_pts, cshape = _grid(box, voxel * factor)
    coarse = field(coarse_pts).reshape(cshape)
    corners = np.stack([coarse[i:cshape[0] - 1 + i, j:cshape[1] - 1 + j, k:cshape[2] - 1 + k]
                        for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    cell = voxel * factor * np.sqrt(3)
    near = (corners.min(0) < 0) & (corners.max(0) > 0) | (np.abs(corners).min(0) < cell)
    near = ndimage.binary_dilation(near, iterations=1)
    fshape = tuple((s - 1) * factor + 1 for s in cshape)
    values = torch.nn.functional.interpolate(torch.as_tensor(coarse, dtype=torch.float32)[None, None],
                                             size=fshape, mode="trilinear", align_corners=True)[0, 0].numpy()
    band = np.zeros(fshape, dtype=bool)
    band[:-1, :-1, :-1] = near.repeat(factor, 0).repeat(factor, 1).repeat(factor, 2)
    band = ndimage.binary_dilation(band, iterations=1)
    idx = np.argwhere(band)
    chunk = 1 << 18
    for s in range(0, len(idx), chunk):
        part = idx[s:s + chunk]
        values[tuple(part.T)] = field(box[0] + voxel * part)
        progress(Progress(min(1.0, (s + chunk) / len(idx)), "meshing",
                          message=f"{min(s + chunk, len(idx))}/{len(idx)} band points"))
    return values


def marching_cubes(values: np.ndarray, origin: np.ndarray, voxel: float) -> trimesh.Trimesh:
    """Zero level set of a grid of signed distances (negative inside), outward-facing, closed at the grid's
    border."""
    padded = np.pad(values, 1, constant_values=max(float(values.max()), voxel))
    if padded.min() >= 0:
        raise N2DError("the field has no inside", "check the masks and camera poses of the session")
    v, f, _, _ = measure.marching_cubes(padded, level=0.0, spacing=(voxel,) * 3)
    return trimesh.Trimesh(v + origin - voxel, f, process=True)


def clean(mesh: trimesh.Trimesh, cfg: MeshConfig) -> trimesh.Trimesh:
    """Largest component, Taubin smoothing, decimation to cfg.target_faces, holes filled, normals outward."""
    parts = mesh.split(only_watertight=False)
    if len(parts) > 1:
        mesh = max(parts, key=lambda m: m.area)
    if cfg.smooth_iterations:
        trimesh.smoothing.filter_taubin(mesh, lamb=0.5, nu=0.53, iterations=cfg.smooth_iterations)
    if cfg.target_faces and len(mesh.faces) > cfg.target_faces:
        v, f = fast_simplification.simplify(mesh.vertices.astype(np.float32), mesh.faces.astype(np.int64),
                                            target_reduction=1.0 - cfg.target_faces / len(mesh.faces))
        mesh = trimesh.Trimesh(v.astype(np.float64), f, process=True)
    mesh = close_holes(remove_pinches(mesh))
    trimesh.repair.fix_normals(mesh)
    return mesh


def remove_pinches(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """The mesh without the faces on edges that more than two faces share (decimation can pinch two sheets of a
    thin part together there); `close_holes` then closes what they leave open."""
    edges, count = np.unique(mesh.edges_sorted, axis=0, return_counts=True)
    pinched = edges[count > 2]
    if not len(pinched):
        return mesh
    face_edges = mesh.edges_sorted.reshape(-1, 3, 2)
    bad = np.zeros(len(mesh.faces), bool)
    for edge in pinched:
        bad |= (face_edges == edge).all(-1).any(-1)
    return trimesh.Trimesh(mesh.vertices, mesh.faces[~bad], process=True)


def close_holes(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Every boundary loop closed by a fan of triangles around its centroid, oriented like its neighbours."""
    edges = mesh.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    _, index, count = np.unique(np.sort(edges, axis=1), axis=0, return_index=True, return_counts=True)
    outgoing = defaultdict(list)
    for a, b in edges[index[count == 1]]:
        outgoing[int(b)].append(int(a))  # a face runs its boundary edge a -> b, so the hole runs b -> a
    loops = []
    for start in list(outgoing):
        path = [start]
        while outgoing[path[-1]]:
            nxt = outgoing[path[-1]].pop()
            if nxt in path:  # a loop closed (where two holes touch, a vertex is passed twice)
                k = path.index(nxt)
                loops.append(path[k:])
                del path[k + 1:]
            else:
                path.append(nxt)
    vertices, faces = list(mesh.vertices), list(mesh.faces)
    for loop in loops:
        if len(loop) < 3:
            continue
        centre = len(vertices)
        vertices.append(mesh.vertices[loop].mean(0))
        faces += [(loop[i], loop[(i + 1) % len(loop)], centre) for i in range(len(loop))]
    return trimesh.Trimesh(np.array(vertices), np.array(faces), process=True)


def extract_mesh(field: Field, search_box: np.ndarray, cfg: MeshConfig,
                 progress: ProgressFn = no_progress) -> trimesh.Trimesh:
    """The clean surface of `field` inside `search_box` (2 x 3, metres)."""
    progress(Progress(0.0, "meshing", message="locating the object"))
    box = locate(field, search_box, cfg.locate_voxel_m)
    box = np.stack([np.maximum(box[0], search_box[0]), np.minimum(box[1], search_box[1])])
    # Start 2.5 voxels below the search box's floor (the plate), so no grid node lies on the plane where the
    # field is 0 and marching cubes closes the bottom cleanly.
    box[0, 2] = search_box[0, 2] - 2.5 * cfg.voxel_m
    values = sample_narrow_band(field, box, cfg.voxel_m, cfg.coarse_factor, progress)
    mesh = marching_cubes(values, box[0], cfg.voxel_m)
    return clean(mesh, cfg)
