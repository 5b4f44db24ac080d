"""Planar faces made flat: large regions of the mesh that lie on one plane to within the reconstruction's
noise are projected onto that plane, and the edges and corners where two or three such regions meet onto
the planes' intersections.

Both reconstructions leave low ripples on surfaces that are flat in truth: the photo-consistency depths of
the fast path and the NeuS surface are each good to a fraction of a pixel, but not everywhere the same
fraction (fast path, captured box: crests 0.6 mm out on faces whose mean plane lies within 0.1 mm of the
truth). The bounding box is made of those crests. A region is grown from the flattest faces over their
neighbours that lie within `distance_px` of its fitted plane and turn less than `max_angle_deg` from it;
it counts as a plane when it is broad (`min_width`, a fraction of the object's diameter) and its vertices
scatter about the plane by no more than noise (`max_scatter_px`). A curved surface (a bottle's body) gives
strips that sag as deep as `distance_px`, far more than the noise, and stays as it was.

The earlier phases fold the surface over here and there: a sliver turned over at a sharp edge (hull pull,
denoising), a thin fin where the hull's roof over an unseen top was refined from both sides. Such faces turn
too far from the plane to grow into its region, yet they stand proud of it by a few tenths of a millimetre,
make the bounding box and render as specks. A plane claims them (`claim_strays`) when they lie within
`distance_px` of it and either face against it or are enclosed by its region alone, and after the snap the
vertices around faces left turned over within a plane slide within it to their neighbours' mean until the
faces untangle (`untangle`), which moves no surface.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy import sparse
from scipy.sparse.csgraph import breadth_first_order, connected_components

from n2d_common.progress import Progress, ProgressFn, no_progress


@dataclass
class PlanesConfig:
    """Flattening of planar regions (both methods)."""

    enabled: bool = True
    """Flatten planar regions (false: keep the surface as it is)."""
    distance_px: float = 3.0
    """A face joins a region when its corners lie within this of the region's plane, in pixels at the object's
    distance (the ripple's amplitude is under one)."""
    max_angle_deg: float = 25.0
    """A face joins a region when its normal turns less than this from the plane's."""
    max_scatter_px: float = 0.5
    """A region is a plane when its vertices scatter about it by less than this (a robust standard deviation), in
    pixels at the object's distance: a curved surface's strip scatters by about a third of `distance_px`."""
    min_width: float = 0.15
    """A region is a plane when it spans at least this fraction of the object's diameter across its narrower
    extent."""

    def __post_init__(self):
        if self.distance_px <= 0 or self.max_scatter_px <= 0 or self.min_width <= 0:
            raise ValueError("planes.distance_px, max_scatter_px and min_width must be > 0")
        if not 0 < self.max_angle_deg < 90:
            raise ValueError(f"planes.max_angle_deg must be in (0, 90), got {self.max_angle_deg}")


def _fit_plane(points: np.ndarray, rounds: int = 8, band: float = 2.0) -> tuple[np.ndarray, float, np.ndarray, float]:
    """A robust plane through `points`: unit normal n and offset d of n.x = d, the points' extents along the
    plane's two in-plane axes (largest first) and their robust scatter about it (1.4826 x the median absolute
    distance). Tukey weights over a narrow `band` (times the scatter) let the fit settle on the layer where most
    of the region agrees: a dent or a bulge of a plain patch (captured box: 1-2 mm over a fifth of a face) is
    weighed out rather than tilting the plane towards it."""
    weight = np.ones(len(points))
    for _ in range(rounds):
        centre = np.average(points, axis=0, weights=weight)
        _, _, axes = np.linalg.svd((points - centre) * np.sqrt(weight)[:, None], full_matrices=False)
        residual = (points - centre) @ axes[2]
        scatter = 1.4826 * float(np.median(np.abs(residual)))
        weight = np.clip(1 - (residual / max(band * scatter, 1e-12)) ** 2, 0, None) ** 2 + 1e-9
    along = (points - centre) @ axes[:2].T
    return axes[2], float(axes[2] @ centre), np.ptp(along, axis=0), scatter


def find_planes(mesh: trimesh.Trimesh, distance_m: float, scatter_m: float, cfg: PlanesConfig,
                fixed: np.ndarray | None = None) -> tuple[np.ndarray, list[tuple[np.ndarray, float]]]:
    """Planar regions of `mesh`: a region index per face (-1: none) and each region's plane (n, d). Faces with
    a `fixed` vertex (the cut on the plate, exact already) join none."""
    faces, vertices = mesh.faces, mesh.vertices
    normals = mesh.face_normals
    pairs = mesh.face_adjacency
    graph = sparse.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(faces),) * 2)
    graph = (graph + graph.T).tocsr()
    bend = np.bincount(pairs.ravel(), np.repeat(mesh.face_adjacency_angles, 2), minlength=len(faces))
    seeds = np.argsort(bend / np.maximum(np.bincount(pairs.ravel(), minlength=len(faces)), 1))
    min_width = cfg.min_width * float(np.linalg.norm(np.ptp(vertices, axis=0)))
    cos_limit = np.cos(np.radians(cfg.max_angle_deg))
    label = np.full(len(faces), -1)
    held = np.zeros(len(faces), dtype=bool) if fixed is None else fixed[faces].any(axis=1)
    tried = held.copy()
    planes: list[tuple[np.ndarray, float]] = []
    for seed in seeds:
        if tried[seed] or label[seed] >= 0:
            continue
        n, d = normals[seed], float(normals[seed] @ vertices[faces[seed, 0]])
        region = np.array([seed])
        for _ in range(3):  # grow from the plane, refit, grow again from the refitted plane
            near = ((label < 0) & ~held & (normals @ n > cos_limit)
                    & (np.abs(vertices @ n - d)[faces].max(axis=1) < distance_m))
            near[seed] = True
            member = sparse.diags(near.astype(float))
            region = breadth_first_order(member @ graph @ member, seed, directed=False, return_predecessors=False)
            n, d, extent, scatter = _fit_plane(vertices[np.unique(faces[region])])
            if n @ normals[seed] < 0:  # the fit's normal has either sign: keep the seed's side
                n, d = -n, -d
        tried[region] = True
        if extent[1] >= min_width and scatter <= scatter_m:
            label[region] = len(planes)
            planes.append((n, d))
    return label, planes


def _stacked(planes: list[tuple[np.ndarray, float]]) -> tuple[np.ndarray, np.ndarray]:
    """The planes' normals (P x 3) and offsets (P)."""
    return np.array([n for n, _ in planes]), np.array([d for _, d in planes])


def _winding(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Per face: the cross product of its edges in winding order (twice its area along its normal)."""
    corners = vertices[faces]
    return np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])


def claim_strays(mesh: trimesh.Trimesh, label: np.ndarray, planes: list[tuple[np.ndarray, float]],
                 distance_m: float, fixed: np.ndarray | None = None) -> np.ndarray:
    """`label` with the faces that belong to a plane's region but were left out of it: faces next to the
    region that face against its plane (a fold, grown a few faces deep), and patches enclosed by the region
    alone (a fin, a speck), in both cases with every corner within `distance_m` of the plane."""
    if not planes:
        return label
    faces, vertices = mesh.faces, mesh.vertices
    normal, offset = _stacked(planes)
    held = np.zeros(len(faces), dtype=bool) if fixed is None else fixed[faces].any(axis=1)
    label = label.copy()

    def within(face: np.ndarray, k: np.ndarray) -> np.ndarray:
        return np.abs(np.einsum("fcx,fx->fc", vertices[faces[face]], normal[k]) - offset[k][:, None]).max(axis=1) \
            < distance_m

    pairs = np.concatenate([mesh.face_adjacency, mesh.face_adjacency[:, ::-1]])
    for _ in range(4):
        face, beside = pairs[(label[pairs[:, 0]] < 0) & (label[pairs[:, 1]] >= 0) & ~held[pairs[:, 0]]].T
        k = label[beside]
        turned = (np.einsum("fx,fx->f", mesh.face_normals[face], normal[k]) < -0.5) & within(face, k)
        if not turned.any():
            break
        label[face[turned]] = k[turned]
    free = (label < 0) & ~held
    inner = pairs[free[pairs[:, 0]] & free[pairs[:, 1]]]
    _, patch = connected_components(sparse.coo_matrix((np.ones(len(inner)), (inner[:, 0], inner[:, 1])),
                                                      shape=(len(faces),) * 2), directed=False)
    edge = pairs[free[pairs[:, 0]] & ~free[pairs[:, 1]]]
    around = np.where(held, -1, label)  # what borders a patch: a region, or the cut on the plate (-1)
    borders = np.unique(np.stack([patch[edge[:, 0]], around[edge[:, 1]]], axis=1), axis=0)
    count = np.bincount(borders[:, 0], minlength=patch.max() + 1)
    for p, k in borders[(count[borders[:, 0]] == 1) & (borders[:, 1] >= 0)]:
        members = np.nonzero(free & (patch == p))[0]
        if within(members, np.full(len(members), k)).all():
            label[members] = k
    return label


def snap_to_planes(vertices: np.ndarray, faces: np.ndarray, label: np.ndarray,
                   planes: list[tuple[np.ndarray, float]], max_move_m: float) -> np.ndarray:
    """Each vertex of a planar region moved to the least-squares point of the planes of the regions around it:
    onto the plane inside a region, onto the intersection line on an edge between two, onto the corner where
    three meet. Where that point lies further than `max_move_m` (nearly parallel planes meet far away), the
    vertex goes to the mean of its projections onto the planes instead."""
    n_v = len(vertices)
    on = label[:, None] >= 0
    pairs = np.unique(np.stack([faces[on[:, 0]].ravel(), np.repeat(label[on[:, 0]], 3)], axis=1), axis=0)
    if not len(pairs):
        return vertices.copy()
    normal, offset = (a[pairs[:, 1]] for a in _stacked(planes))
    system = np.zeros((n_v, 3, 3))
    rhs = np.zeros((n_v, 3))
    np.add.at(system, pairs[:, 0], normal[:, :, None] * normal[:, None, :])
    np.add.at(rhs, pairs[:, 0], normal * offset[:, None])
    count = np.bincount(pairs[:, 0], minlength=n_v)
    moved = count > 0
    ridge = 1e-6  # keeps the system regular along the free directions (the vertex stays put along them)
    x0 = vertices[moved]
    solved = np.linalg.solve(system[moved] + ridge * np.eye(3), (rhs[moved] + ridge * x0)[:, :, None])[:, :, 0]
    projections = np.zeros((n_v, 3))
    np.add.at(projections, pairs[:, 0],
              vertices[pairs[:, 0]] - (np.einsum("pc,pc->p", vertices[pairs[:, 0]], normal) - offset)[:, None] * normal)
    mean = projections[moved] / count[moved, None]
    far = np.linalg.norm(solved - x0, axis=1) > max_move_m
    out = vertices.copy()
    out[moved] = np.where(far[:, None], mean, solved)
    return out


def untangle(vertices: np.ndarray, faces: np.ndarray, label: np.ndarray, planes: list[tuple[np.ndarray, float]],
             fixed: np.ndarray | None = None, rings: int = 2, iterations: int = 30) -> tuple[np.ndarray, int]:
    """`vertices` with the faces turned over within their plane untangled, and how many stay turned: the vertices
    within `rings` of such a face that lie inside one region (all their faces on its plane, not `fixed`) move to
    the mean of their neighbours, projected back onto the plane, `iterations` times."""
    if not planes:
        return vertices, 0
    normal, offset = _stacked(planes)
    n_v = len(vertices)

    def turned(points: np.ndarray) -> np.ndarray:
        return (label >= 0) & (np.einsum("fx,fx->f", _winding(points, faces), normal[np.maximum(label, 0)]) < 0)

    over = turned(vertices)
    if not over.any():
        return vertices, 0
    pairs = np.unique(np.stack([faces.ravel(), np.repeat(label, 3)], axis=1), axis=0)
    alone = np.bincount(pairs[:, 0], minlength=n_v) == 1
    region = np.full(n_v, -1)
    region[pairs[alone[pairs[:, 0]], 0]] = pairs[alone[pairs[:, 0]], 1]
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    adjacency = sparse.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n_v, n_v)).tocsr()
    adjacency = ((adjacency + adjacency.T) > 0).astype(float)
    near = np.zeros(n_v, dtype=bool)
    near[faces[over].ravel()] = True
    for _ in range(rings):
        near |= adjacency @ near > 0
    if fixed is not None:
        near &= ~fixed
    move = np.nonzero(near & (region >= 0))[0]
    n, d = normal[region[move]], offset[region[move]]
    degree = np.asarray(adjacency.sum(axis=1)).ravel()[move, None]
    out = vertices.copy()
    for _ in range(iterations):
        mean = adjacency[move] @ out / degree
        out[move] = mean - (np.einsum("vx,vx->v", mean, n) - d)[:, None] * n
    return out, int(turned(out).sum())


def flatten_planes(mesh: trimesh.Trimesh, pixel_m: float, cfg: PlanesConfig, fixed: np.ndarray | None = None,
                   progress: ProgressFn = no_progress) -> tuple[trimesh.Trimesh, dict | None]:
    """`mesh` with its planar regions flattened, and what was found (None when disabled). Faces with a `fixed`
    vertex (the cut on the plate) join no region, so those vertices stay."""
    if not cfg.enabled:
        return mesh, None
    progress(Progress(0.0, "planes", message="finding planar regions"))
    distance = cfg.distance_px * pixel_m
    found, planes = find_planes(mesh, distance, cfg.max_scatter_px * pixel_m, cfg, fixed)
    label = claim_strays(mesh, found, planes, distance, fixed)
    for _ in range(3):  # claims that put a face's three corners on one edge line (a sliver along it) give way
        vertices = snap_to_planes(mesh.vertices, mesh.faces, label, planes, 2 * distance)
        sliver = 0.5 * np.linalg.norm(_winding(vertices, mesh.faces), axis=1) < (0.05 * pixel_m) ** 2
        flat = np.zeros(len(vertices), dtype=bool)
        flat[mesh.faces[sliver].ravel()] = True
        undo = (label != found) & flat[mesh.faces].any(axis=1)
        if not undo.any():
            break
        label[undo] = found[undo]
    vertices, turned = untangle(vertices, mesh.faces, label, planes, fixed)
    moved = np.linalg.norm(vertices - mesh.vertices, axis=1)
    stats = {"planes": len(planes), "face_fraction": round(float(np.mean(label >= 0)), 4),
             "normals": [np.round(n, 4).tolist() for n, _ in planes],
             "claimed_faces": int(np.sum(label != found)), "turned_faces": turned,
             "max_move_mm": round(1000 * float(moved.max(initial=0.0)), 3)}
    return trimesh.Trimesh(vertices, mesh.faces, process=False), stats
