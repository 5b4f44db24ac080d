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
from scipy.spatial.distance import cdist

from n2d_common.errors import ContractError


def diameter(vertices: np.ndarray) -> float:
    """Largest distance between two of the points (BOP's object diameter), in their unit.

    Over the convex hull's vertices, in blocks of about 4 M pairs: a finely tessellated convex body (a sphere of
    40k vertices) has all its vertices on the hull, and all pairs at once would take tens of GB."""
    hull = vertices[ConvexHull(vertices).vertices]
    rows = max(1, (1 << 22) // len(hull))
    best = max(float(cdist(hull[i:i + rows], hull[i:], "sqeuclidean").max()) for i in range(0, len(hull), rows))
    return float(np.sqrt(best))


def models_info(vertices: np.ndarray, symmetries: dict | None = None) -> dict:
    """BOP models_info entry of object-frame `vertices` (metres in, millimetres out)."""
    mm = 1000.0 * vertices
    lo, size = mm.min(0), mm.max(0) - mm.min(0)
    info = {"diameter": round(diameter(mm), 4)}
    info.update({f"min_{a}": round(float(v), 4) for a, v in zip("xyz", lo)})
    info.update({f"size_{a}": round(float(v), 4) for a, v in zip("xyz", size)})
    info.update(symmetries or {})
    return info


def _load_obj(path: Path) -> trimesh.Trimesh:
    """trimesh's reading of an OBJ file; ContractError when it is missing or trimesh cannot parse it."""
    try:
        return trimesh.load(path, force="mesh", process=False)
    except (OSError, ValueError, IndexError, KeyError, TypeError) as exc:
        raise ContractError(f"cannot read the mesh {path} ({type(exc).__name__}: {exc})",
                            "re-run n2d reconstruct for this model, or check the mesh's export") from None


def read_model_mesh(directory: Path) -> trimesh.Trimesh:
    """The mesh of a model directory (metres, object frame), without its texture."""
    mesh = _load_obj(Path(directory) / "mesh.obj")
    return trimesh.Trimesh(mesh.vertices, mesh.faces, process=True)


def read_textured_model(directory: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(V x 3 vertices in metres, F x 3 faces, F x 3 x 2 per-corner UVs (v up, as in OBJ), H x W x 3 uint8 albedo)
    of a model directory's mesh.obj; a mesh without texture coordinates gets its material's plain colour."""
    path = Path(directory) / "mesh.obj"
    if not path.is_file():
        raise ContractError(f"{directory} has no mesh.obj", "give a model directory (from n2d reconstruct)")
    mesh = _load_obj(path)
    faces = np.asarray(mesh.faces, np.int64)
    if len(faces) == 0:
        raise ContractError(f"{path} has no faces", "check the model's export")
    uv = getattr(mesh.visual, "uv", None)
    material = getattr(mesh.visual, "material", None)
    image = getattr(material, "image", None)
    if uv is None or len(uv) != len(mesh.vertices) or image is None:
        colour = np.asarray(getattr(material, "diffuse", [200, 200, 200, 255]), float)[:3]
        return (np.asarray(mesh.vertices, float), faces, np.zeros((len(faces), 3, 2)),
                np.full((2, 2, 3), colour, np.uint8))
    try:
        albedo = np.asarray(image.convert("RGB"))
    except OSError as exc:  # PIL decodes the texture only now
        raise ContractError(f"cannot read the texture of {path} ({exc})",
                            "re-run n2d reconstruct for this model, or restore its albedo.png") from None
    return np.asarray(mesh.vertices, float), faces, np.asarray(uv, float)[faces], albedo
