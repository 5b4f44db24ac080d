"""Model writers: the object frame, OBJ + MTL + PNG and GLB in metres, and BOP's models_info.json in mm.

The object frame (design.md): origin at the centre of the mesh's axis-aligned bounding box in the
turntable frame, axes parallel to the turntable's, so Z is up as the object stood on the plate.
`T_turntable_obj` is recorded in the model's manifest so other stages can place the model back.
glTF is Y up, so the GLB holds the same mesh rotated by +90 degrees about X (x, y, z) -> (x, z, -y).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image

from n2d_common.contracts import atomic_write_bytes, atomic_write_json, atomic_write_text
from n2d_common.formats.model import models_info
from n2d_common.frames import make_T
from n2d_common.images import write_png
from n2d_reconstruct.texture import TexturedMesh

GLTF_FROM_Z_UP = np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])
"""4x4 rotation from a Z-up frame into glTF's Y-up frame."""


def object_frame(vertices: np.ndarray) -> np.ndarray:
    """4 x 4 T_turntable_obj: the object frame at the bounding-box centre of turntable-frame `vertices`."""
    return make_T(np.eye(3), (vertices.min(0) + vertices.max(0)) / 2)


def obj_text(tm: TexturedMesh, name: str) -> str:
    """Wavefront OBJ of a textured mesh (positions in metres, one UV per vertex), using mesh.mtl."""
    lines = [f"# n2d model '{name}': metres, object frame at the bounding-box centre, Z up", "mtllib mesh.mtl",
             f"o {name}"]
    lines += [f"v {x:.7f} {y:.7f} {z:.7f}" for x, y, z in tm.vertices]
    lines += [f"vt {u:.6f} {v:.6f}" for u, v in tm.uvs]
    lines += [f"usemtl {name}", "s off"]
    lines += [f"f {a}/{a} {b}/{b} {c}/{c}" for a, b, c in tm.faces + 1]
    return "\n".join(lines) + "\n"


def mtl_text(name: str) -> str:
    """The material: an unlit-looking diffuse albedo texture."""
    return (f"newmtl {name}\nKa 1.000 1.000 1.000\nKd 1.000 1.000 1.000\nKs 0.000 0.000 0.000\n"
            "Ns 10.0\nd 1.0\nillum 1\nmap_Kd albedo.png\n")


def glb_bytes(tm: TexturedMesh) -> bytes:
    """Binary glTF of the textured mesh, rotated into glTF's Y-up frame."""
    material = trimesh.visual.material.PBRMaterial(baseColorTexture=Image.fromarray(tm.albedo),
                                                   metallicFactor=0.0, roughnessFactor=1.0)
    mesh = trimesh.Trimesh(tm.transformed(GLTF_FROM_Z_UP).vertices, tm.faces, process=False,
                           visual=trimesh.visual.TextureVisuals(uv=tm.uvs, material=material))
    buffer = io.BytesIO()
    mesh.export(buffer, file_type="glb")
    return buffer.getvalue()


def write_model(directory: Path, tm: TexturedMesh, name: str, symmetries: dict | None = None) -> dict:
    """Write mesh.obj, mesh.mtl, albedo.png, mesh.glb and models_info.json of the object-frame mesh `tm`;
    returns its models_info entry."""
    atomic_write_text(directory / "mesh.obj", obj_text(tm, name))
    atomic_write_text(directory / "mesh.mtl", mtl_text(name))
    write_png(directory / "albedo.png", tm.albedo)
    atomic_write_bytes(directory / "mesh.glb", glb_bytes(tm))
    info = models_info(tm.vertices, symmetries)
    atomic_write_json(directory / "models_info.json", {"1": info})
    return info
