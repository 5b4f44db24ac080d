"""The fast path's photo-consistency refinement: the views compared per vertex, the silhouette anchors and the
membrane that turns found depths into vertex displacements."""

import numpy as np
import pytest
import trimesh

from n2d_reconstruct.data import Views
from n2d_reconstruct.refine import RefineConfig, pick_views, silhouette_anchors, smooth_displacements


def _ring(views: int, elevation_deg: float = 45.0, distance_m: float = 0.5) -> np.ndarray:
    azimuth = np.arange(views) * 2 * np.pi / views
    el = np.radians(elevation_deg)
    return distance_m * np.stack([np.cos(el) * np.cos(azimuth), np.cos(el) * np.sin(azimuth),
                                  np.full(views, np.sin(el))], 1)


def _frontal(eyes: np.ndarray, normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    to_cam = eyes / np.linalg.norm(eyes, axis=1, keepdims=True)
    cos = (to_cam @ normal)[None]
    return cos, cos > 0.4


def _angles_deg(eyes: np.ndarray, picked: np.ndarray) -> np.ndarray:
    d = eyes[picked] / np.linalg.norm(eyes[picked], axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip(d @ d.T, -1, 1)))[np.triu_indices(len(picked), 1)]


def test_a_dense_ring_gives_the_baselines_of_a_sparse_one():
    cfg = RefineConfig()
    normal = np.array([1.0, 0.0, 0.0])
    sparse_eyes, dense_eyes = _ring(36), _ring(72)
    sparse, ok_sparse = pick_views(np.zeros((1, 3)), sparse_eyes, *_frontal(sparse_eyes, normal), cfg)
    dense, ok_dense = pick_views(np.zeros((1, 3)), dense_eyes, *_frontal(dense_eyes, normal), cfg)
    assert ok_sparse.all() and ok_dense.all()
    cos, _ = _frontal(sparse_eyes, normal)
    # 36 views, 7 degrees apart: the plain most frontal seven, the most frontal first
    assert sparse[0, 0] == np.argmax(cos[0])
    assert set(sparse[0]) == set(np.argsort(-cos[0])[:cfg.views_per_vertex])
    # 72 views: every other one, so the same directions and baselines as 36
    assert _angles_deg(dense_eyes, dense[0]).min() >= cfg.min_separation_deg
    assert np.allclose(np.sort(_angles_deg(dense_eyes, dense[0])), np.sort(_angles_deg(sparse_eyes, sparse[0])))


def test_no_separation_gives_the_most_frontal_views():
    cfg = RefineConfig(min_separation_deg=0.0)
    eyes = _ring(72)
    cos, visible = _frontal(eyes, np.array([0.6, 0.0, 0.8]))
    picked, ok = pick_views(np.zeros((1, 3)), eyes, cos, visible, cfg)
    assert ok.all()
    assert list(picked[0]) == list(np.argsort(-cos[0], kind="stable")[:cfg.views_per_vertex])


def test_a_vertex_seen_by_too_few_views_is_not_usable():
    cfg = RefineConfig()
    eyes = _ring(36)
    cos, visible = _frontal(eyes, np.array([1.0, 0.0, 0.0]))
    visible[:, np.argsort(-cos[0])[3:]] = False
    _, ok = pick_views(np.zeros((1, 3)), eyes, cos, visible, cfg)
    assert not ok.any()


def test_silhouette_anchors_hold_the_least_moved_vertex_on_an_outline_ray():
    """One camera at the origin looking down +Z; the mask is a rectangle. Three vertices lie on the ray through
    an outline pixel (a roof over an edge, and the edge itself), one on the ray of an inner pixel."""
    K = np.array([[100.0, 0.0, 32.0], [0.0, 100.0, 24.0], [0.0, 0.0, 1.0]])
    mask = np.zeros((48, 64), bool)
    mask[10:40, 20:50] = True
    views = Views(np.zeros((1, 48, 64, 3), np.uint8), mask[None], K, np.eye(4)[None], ["0000.png"])
    ray = np.array([(20 - 32) / 100.0, (25 - 24) / 100.0, 1.0])  # pixel (20, 25): on the mask's left outline
    inner = np.array([(35 - 32) / 100.0, (25 - 24) / 100.0, 1.0])
    vertices = np.stack([0.40 * ray, 0.45 * ray, 0.50 * ray, 0.5 * inner])
    depth = np.array([0.004, 0.0005, 0.002, 0.0])  # the edge (second) moved least; the inner vertex is no rim
    held = silhouette_anchors(vertices, depth, views, radius_px=1.0)
    assert held.tolist() == [False, True, False, False]
    # nothing is held where no vertex lies near an outline pixel's ray
    assert not silhouette_anchors(vertices[3:], depth[3:], views, radius_px=1.0).any()


def _ridge_on_a_plane() -> tuple[trimesh.Trimesh, np.ndarray]:
    """A 20 x 20 mm grid, 1 mm apart, flat but for a ridge 4 mm high along x (a hull's roof crest left over a
    plain top); and found displacements: zero on the flat part, none (NaN) on the ridge."""
    xs = np.arange(-10, 11) * 0.001
    x, y = np.meshgrid(xs, xs, indexing="ij")
    z = np.maximum(0.0, 0.004 - 2 * np.abs(y))
    idx = np.arange(x.size).reshape(x.shape)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    mesh = trimesh.Trimesh(np.stack([x.ravel(), y.ravel(), z.ravel()], 1), faces, process=False)
    found = np.where((z.ravel() == 0)[:, None], 0.0, np.nan) * np.ones((1, 3))
    return mesh, found


def test_the_bending_term_brings_down_a_crest_where_nothing_was_found():
    mesh, found = _ridge_on_a_plane()
    kept = mesh.vertices + smooth_displacements(mesh, found, RefineConfig(flatten=0.0))
    assert kept[:, 2].max() == pytest.approx(0.004, abs=1e-6)  # interpolated displacements keep the hull's crest
    flattened = mesh.vertices + smooth_displacements(mesh, found, RefineConfig())
    assert flattened[:, 2].max() < 0.5 * 0.004
    flat = np.isfinite(found).all(1)
    assert np.abs(flattened[flat, 2]).max() < 1e-5  # the found surface stays where it was found
    with pytest.raises(ValueError, match="flatten"):
        RefineConfig(flatten=-1.0)
