"""The model directory (`kind: model`), as every stage reads it: the mesh in metres in the object frame, and BOP's
models_info.json entry (millimetres) with its diameter, extent and symmetries.

A model directory holds mesh.obj + mesh.mtl + albedo.png (and mesh.glb), models_info.json ({"1": entry}) and the
n2d.json manifest; docs/formats.md describes it. Writers live with the stage that makes models (`n2d_reconstruct`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import ConvexHull


def diameter(vertices: np.ndarray) -> float:
    """Largest distance between two of the points (BOP's object diameter), in their unit."""
    hull = vertices[ConvexHull(vertices).vertices]
    return float(np.sqrt(((hull[:, None] - hull[None]) ** 2).sum(-1)).max())


def models_info(vertices: np.ndarray, symmetries: dict | None = None) -> dict:
    """BOP models_info entry of object-frame `vertices` (metres in, millimetres out)."""
    mm = 1000.0 * vertices
    lo, size = mm.min(0), mm.max(0) - mm.min(0)
    info = {"diameter": round(diameter(mm), 4)}
    info.update({f"min_{a}": round(float(v), 4) for a, v in zip("xyz", lo)})
    info.update({f"size_{a}": round(float(v), 4) for a, v in zip("xyz", size)})
    info.update(symmetries or {})
    return info


def read_model_mesh(directory: Path) -> trimesh.Trimesh:
    """The mesh of a model directory (metres, object frame), without its texture."""
    mesh = trimesh.load(directory / "mesh.obj", force="mesh", process=False)
    return trimesh.Trimesh(mesh.vertices, mesh.faces, process=True)
