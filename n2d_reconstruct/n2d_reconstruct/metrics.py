"""Quality metrics of the reconstruction stage: renders against held-out photos (PSNR, SSIM, FLIP) and
a reconstructed mesh against the ground truth (chamfer distance, F-score).

Pure functions over arrays. Images are H x W x 3, uint8 (0..255) or float in [0, 1]; each is taken to
float64 in [0, 1], so the data range is 1 (255 in uint8 units). A mask is H x W bool: the pixels a
metric averages over (default: all). Points are N x 3, meshes V x 3 vertices and F x 3 faces; distances
in metres.
"""

from __future__ import annotations

import math

import flip_evaluator
import numpy as np
from scipy.spatial import cKDTree
from skimage.metrics import structural_similarity

from n2d_common.geometry import sample_surface_faces

SSIM_SIGMA = 1.5
"""Gaussian SSIM window (Wang et al. 2004): sigma 1.5 px, truncated at 3.5 sigma, 11 x 11 taps."""
SSIM_RADIUS = int(3.5 * SSIM_SIGMA + 0.5)
"""Half width of the SSIM window, px: skimage leaves this border out of its mean."""
FSCORE_THRESHOLD = 0.001
"""Default F-score distance threshold, metres."""
SURFACE_CANDIDATES = 8
"""Nearest reference points (the surface's samples, face centroids and face corners) whose faces, and
those faces' edge neighbours, are tried when measuring a point's distance to a surface."""


def psnr(reference: np.ndarray, test: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Peak signal-to-noise ratio, dB, data range 1: 10 log10(1 / MSE) over the mask; inf when equal."""
    ref, tst = _unit_pair(reference, test)
    err = (ref - tst) ** 2
    mse = float(_masked(err, mask).mean())
    return math.inf if mse == 0 else 10.0 * math.log10(1.0 / mse)


def ssim(reference: np.ndarray, test: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean structural similarity (1 when equal) over the mask, from skimage's Gaussian SSIM map.

    skimage.metrics.structural_similarity(gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
    channel_axis=-1, data_range=1), averaged over channels and the mask's pixels; like skimage, pixels
    within SSIM_RADIUS of the image border are left out, so a full mask gives skimage's value. The map is
    computed on the mask's bounding box plus a window's margin only, which changes no value inside.
    """
    ref, tst = _unit_pair(reference, test)
    h, w = ref.shape[:2]
    interior = np.zeros((h, w), bool)
    interior[SSIM_RADIUS:h - SSIM_RADIUS, SSIM_RADIUS:w - SSIM_RADIUS] = True
    if mask is None:
        window = (slice(0, h), slice(0, w))
        keep = interior
    else:
        rows, cols = np.nonzero(mask)
        if len(rows) == 0:
            raise ValueError("empty mask")
        margin = 2 * SSIM_RADIUS + 1
        window = (slice(max(rows.min() - margin, 0), rows.max() + margin + 1),
                  slice(max(cols.min() - margin, 0), cols.max() + margin + 1))
        keep = mask & interior
    _, ssim_map = structural_similarity(ref[window], tst[window], gaussian_weights=True, sigma=SSIM_SIGMA,
                                        use_sample_covariance=False, channel_axis=-1, data_range=1.0, full=True)
    return float(_masked(ssim_map, keep[window]).mean())


def flip(reference: np.ndarray, test: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean NVIDIA FLIP error (LDR, sRGB inputs, 67 pixels per degree) over the mask: 0 when equal, up to 1."""
    ref, tst = _unit_pair(reference, test)
    error, _, _ = flip_evaluator.evaluate(ref, tst, "LDR", applyMagma=False, computeMeanError=False)
    return float(_masked(error[..., 0], mask).mean())


def chamfer(points_a: np.ndarray, points_b: np.ndarray) -> dict:
    """Symmetric chamfer distance between point sets, metres: {"a_to_b": mean over a of the distance to
    the nearest point of b, "b_to_a": the other way, "chamfer": mean of the two}."""
    return _chamfer(_nearest(points_a, points_b), _nearest(points_b, points_a))


def fscore(points_a: np.ndarray, points_b: np.ndarray, threshold: float) -> dict:
    """F-score at `threshold` metres, a the reconstruction, b the ground truth: {"precision": fraction of a
    within the threshold of b, "recall": fraction of b within the threshold of a, "fscore": their harmonic
    mean (0 when both are 0)}."""
    return _fscore(_nearest(points_a, points_b), _nearest(points_b, points_a), threshold)


def mesh_distances(vertices_a: np.ndarray, faces_a: np.ndarray, vertices_b: np.ndarray, faces_b: np.ndarray,
                   n: int = 100_000, threshold: float = FSCORE_THRESHOLD, seed: int = 0,
                   below_z: float | None = None) -> dict:
    """Chamfer distance and F-score between two meshes, a the reconstruction, b the ground truth.

    n points are sampled on each surface and measured against the other surface, not its samples: each
    point's distance is the exact distance to the nearest of its candidate faces there, the faces of its
    SURFACE_CANDIDATES nearest reference points (the other surface's samples, face centroids and face
    corners) and their edge neighbours (vertices welded by position). That is never more than the
    distance to the nearest sample and, unlike it, does not add the sampling spacing (about
    0.5 sqrt(area / n)) to every distance; it exceeds the exact distance only where the nearest face is
    not a candidate (a mesh against itself, n = 20k: exact to 1e-16 m for a sphere of 1280 or 20k faces
    and a box; for a 64-sided cylinder, whose caps are fans of slivers, mean 1e-7 m, at most 0.7 mm).
    `below_z`: only the samples of either surface at or below this height are measured (the underside).
    Returns the keys of `chamfer` and `fscore` (metres).
    """
    rng = np.random.default_rng(seed)
    points_a, face_a = sample_surface_faces(vertices_a, faces_a, n, rng)
    points_b, face_b = sample_surface_faces(vertices_b, faces_b, n, rng)
    if below_z is not None:
        a, b = points_a[:, 2] <= below_z, points_b[:, 2] <= below_z
        points_a, face_a, points_b, face_b = points_a[a], face_a[a], points_b[b], face_b[b]
    a_to_b = _surface_distance(points_a, np.asarray(vertices_b, float)[faces_b], points_b, face_b)
    b_to_a = _surface_distance(points_b, np.asarray(vertices_a, float)[faces_a], points_a, face_a)
    return _chamfer(a_to_b, b_to_a) | _fscore(a_to_b, b_to_a, threshold)


def _unit_pair(reference: np.ndarray, test: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Both images as float64 in [0, 1], after checking they match."""
    if reference.shape != test.shape:
        raise ValueError(f"image shapes differ: {reference.shape} vs {test.shape}")
    return _unit(reference), _unit(test)


def _unit(image: np.ndarray) -> np.ndarray:
    if image.dtype == np.uint8:
        return image / 255.0
    if not np.issubdtype(image.dtype, np.floating):
        raise ValueError(f"images are uint8 or float in [0, 1], not {image.dtype}")
    return image.astype(np.float64)


def _masked(values: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    """The values (H x W or H x W x C) at the mask's pixels; all of them without a mask."""
    if mask is None:
        return values
    selected = values[np.asarray(mask, bool)]
    if selected.size == 0:
        raise ValueError("empty mask")
    return selected


def _nearest(points: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """Distance from each point to the nearest target point."""
    return cKDTree(targets).query(points)[0]


def _surface_distance(points: np.ndarray, triangles: np.ndarray, samples: np.ndarray, sample_face: np.ndarray
                      ) -> np.ndarray:
    """Distance from each of N points to a surface of F x 3 x 3 triangles, with M x 3 samples on it (on
    faces `sample_face`): the nearest of the candidate faces (see `mesh_distances`)."""
    count = len(triangles)
    reference = np.concatenate([samples, triangles.mean(1), triangles.reshape(-1, 3)])
    reference_face = np.concatenate([sample_face, np.arange(count), np.repeat(np.arange(count), 3)])
    _, nearest = cKDTree(reference).query(points, k=SURFACE_CANDIDATES)
    face = reference_face[nearest]
    face = np.concatenate([face, _edge_neighbours(triangles)[face].reshape(len(points), -1)], 1)
    pair = np.unique(np.arange(len(points))[:, None] * count + face)  # (point, face), sorted by point
    point, face = np.divmod(pair, count)
    d = _point_triangle_distance(points[point], triangles[face])
    return np.minimum.reduceat(d, np.flatnonzero(np.r_[True, point[1:] != point[:-1]]))


def _edge_neighbours(triangles: np.ndarray) -> np.ndarray:
    """F x 3: the face across edge k (opposite vertex k) of each of F x 3 x 3 triangles, vertices welded
    by position; the face itself on a boundary edge; around an edge of more than two faces, the next one."""
    _, vertex = np.unique(triangles.reshape(-1, 3), axis=0, return_inverse=True)
    vertex = vertex.reshape(-1, 3)
    edges = np.sort(np.stack([vertex[:, [1, 2]], vertex[:, [2, 0]], vertex[:, [0, 1]]], 1), axis=2)
    _, edge = np.unique(edges.reshape(-1, 2), axis=0, return_inverse=True)
    order = np.argsort(edge.ravel(), kind="stable")  # the face-edges of each edge, consecutive
    same = edge.ravel()[order]
    first = np.r_[True, same[1:] != same[:-1]]
    last = np.r_[same[1:] != same[:-1], True]
    group_start = np.maximum.accumulate(np.where(first, np.arange(len(same)), 0))
    neighbour = np.empty(len(same), np.int64)
    neighbour[order] = order[np.where(last, group_start, np.arange(len(same)) + 1)]
    return (neighbour // 3).reshape(-1, 3)


def _point_triangle_distance(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Exact distance from N x 3 points to N x 3 x 3 triangles (degenerate ones as their edges)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    normal = np.cross(b - a, c - a)
    nn = np.einsum("ij,ij->i", normal, normal)
    sides = [np.einsum("ij,ij->i", np.cross(q - o, p - o), normal) for o, q in ((a, b), (b, c), (c, a))]
    over_face = (nn > 0) & (sides[0] >= 0) & (sides[1] >= 0) & (sides[2] >= 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        plane = np.abs(np.einsum("ij,ij->i", p - a, normal)) / np.sqrt(nn)
    edges = np.min([_point_segment_distance(p, o, q) for o, q in ((a, b), (b, c), (c, a))], axis=0)
    return np.where(over_face, plane, edges)


def _point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    length2 = np.einsum("ij,ij->i", ab, ab)
    t = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.where(length2 > 0, length2, 1.0), 0.0, 1.0)
    return np.linalg.norm(p - a - t[:, None] * ab, axis=1)


def _chamfer(a_to_b: np.ndarray, b_to_a: np.ndarray) -> dict:
    ab, ba = float(a_to_b.mean()), float(b_to_a.mean())
    return {"a_to_b": ab, "b_to_a": ba, "chamfer": 0.5 * (ab + ba)}


def _fscore(a_to_b: np.ndarray, b_to_a: np.ndarray, threshold: float) -> dict:
    precision, recall = float((a_to_b < threshold).mean()), float((b_to_a < threshold).mean())
    total = precision + recall
    return {"precision": precision, "recall": recall, "fscore": 2 * precision * recall / total if total else 0.0}
