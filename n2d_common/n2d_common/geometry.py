"""Geometry helpers shared by the stages: points sampled uniformly over a triangle mesh's surface.

Plain numpy over V x 3 vertices and F x 3 faces (any unit; the points come out in it).
"""

from __future__ import annotations

import numpy as np


def sample_surface(vertices: np.ndarray, faces: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """n x 3 points uniformly distributed over the surface (faces drawn by area)."""
    return sample_surface_faces(vertices, faces, n, np.random.default_rng(seed))[0]


def sample_surface_faces(vertices: np.ndarray, faces: np.ndarray, n: int, rng: np.random.Generator
            ) -> tuple[np.ndarray, np.ndarray]:
    """(n x 3 uniform surface points, n face index of each)."""
    tri = np.asarray(vertices, float)[faces]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    face = rng.choice(len(tri), size=n, p=area / area.sum())
    r1, r2 = rng.random((2, n, 1))
    s = np.sqrt(r1)
    t = tri[face]
    return (1 - s) * t[:, 0] + s * (1 - r2) * t[:, 1] + s * r2 * t[:, 2], face
