"""Bilateral normal filtering: ripples on flat faces flatten to their mean plane, edges and corners stay,
curved surfaces do not shrink, fixed vertices do not move."""

import numpy as np
import pytest
import trimesh

from n2d_reconstruct.denoise import DenoiseConfig, denoise

SIZE = np.array([0.09, 0.06, 0.14])


def _rippled(mesh: trimesh.Trimesh, amplitude: float, seed: int = 0) -> trimesh.Trimesh:
    """The mesh with each vertex moved along its normal by Gaussian noise of this standard deviation."""
    noise = np.random.default_rng(seed).normal(0.0, amplitude, len(mesh.vertices))
    return trimesh.Trimesh(mesh.vertices + noise[:, None] * mesh.vertex_normals, mesh.faces, process=False)


def _box() -> trimesh.Trimesh:
    box = trimesh.creation.box(SIZE)
    vertices, faces = trimesh.remesh.subdivide_to_size(box.vertices, box.faces, max_edge=0.004)
    return trimesh.Trimesh(vertices, faces)


def _distance_to_box(points: np.ndarray) -> np.ndarray:
    """Unsigned distance to the surface of the box of SIZE centred at the origin."""
    q = np.abs(points) - SIZE / 2
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
    return np.where(outside > 0, outside, -q.max(axis=1))


@pytest.mark.slow
def test_denoise_flattens_a_rippled_box_and_keeps_its_corners():
    noisy = _rippled(_box(), 0.0003)
    out = denoise(noisy, DenoiseConfig())
    assert out.is_watertight and len(out.faces) == len(noisy.faces)
    before = np.abs(noisy.extents - SIZE).max()
    after = np.abs(out.extents - SIZE).max()
    assert after < 0.2 * before, (before, after)
    assert after < 0.0004
    # every vertex ends near the true surface: the box's faces, edges and corners are where they were
    distance = _distance_to_box(out.vertices)
    assert np.percentile(distance, 99) < 0.00015 and distance.max() < 0.0005, distance.max()
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * SIZE / 2
    nearest = np.linalg.norm(out.vertices[None] - corners[:, None], axis=2).min(axis=1)
    assert nearest.max() < 0.0015, nearest


@pytest.mark.slow
def test_denoise_does_not_shrink_a_sphere():
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.05)
    noisy = _rippled(sphere, 0.0003, seed=1)
    out = denoise(noisy, DenoiseConfig())
    radius_before = np.linalg.norm(noisy.vertices, axis=1)
    radius = np.linalg.norm(out.vertices, axis=1)
    assert abs(radius.mean() - 0.05) < 0.0001, radius.mean()
    assert radius.std() < 0.25 * radius_before.std(), (radius_before.std(), radius.std())


def test_denoise_keeps_fixed_vertices_and_can_be_off():
    noisy = _rippled(_box(), 0.0003)
    fixed = noisy.vertices[:, 2] < -SIZE[2] / 2 + 0.001
    out = denoise(noisy, DenoiseConfig(iterations=20, vertex_iterations=10), fixed=fixed)
    assert np.array_equal(out.vertices[fixed], noisy.vertices[fixed])
    assert not np.allclose(out.vertices[~fixed], noisy.vertices[~fixed])
    assert denoise(noisy, DenoiseConfig(iterations=0)) is noisy


def test_denoise_config_is_checked():
    with pytest.raises(ValueError, match="sigma_r"):
        DenoiseConfig(sigma_r=0.0)
    with pytest.raises(ValueError, match="rings"):
        DenoiseConfig(rings=0)


def test_denoise_survives_a_degenerate_face():
    box = _rippled(_box(), 0.0003)
    n = len(box.vertices)  # plus a zero-area face on three coincident vertices of its own: no neighbour has area
    mesh = trimesh.Trimesh(np.vstack([box.vertices, np.zeros((3, 3))]), np.vstack([box.faces, [[n, n + 1, n + 2]]]),
                           process=False)
    out = denoise(mesh, DenoiseConfig(iterations=10, vertex_iterations=10))
    assert np.isfinite(out.vertices).all()
