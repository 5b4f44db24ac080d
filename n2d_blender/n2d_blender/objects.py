"""Objects: mesh objects from arrays, procedural primitives, n2d models, and clearing a scene between frames."""

from __future__ import annotations

from pathlib import Path

import bmesh
import bpy
import numpy as np

from n2d_common.errors import ContractError


def link(obj: bpy.types.Object, parent: bpy.types.Object | None = None) -> bpy.types.Object:
    """Link `obj` into the scene (optionally under `parent`) and return it."""
    bpy.context.scene.collection.objects.link(obj)
    obj.parent = parent
    return obj


def mesh_object(name: str, verts, faces, uvs=None, parent=None) -> bpy.types.Object:
    """A mesh object from vertex and face lists; `uvs` holds one (u, v) per vertex (v up)."""
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata([tuple(map(float, v)) for v in verts], [], [tuple(map(int, f)) for f in faces])
    if uvs is not None:
        layer = mesh.uv_layers.new(name="UVMap")
        flat = [uvs[i] for f in faces for i in f]
        layer.data.foreach_set("uv", np.asarray(flat, dtype=np.float32).ravel())
    mesh.validate()
    return link(bpy.data.objects.new(name, mesh), parent)


def box(name: str, size, location=(0.0, 0.0, 0.0), rot_z: float = 0.0, parent=None) -> bpy.types.Object:
    """An axis-aligned box of `size` (x, y, z) centred at `location`, turned by `rot_z` about Z."""
    sx, sy, sz = (s / 2 for s in size)
    verts = [(x, y, z) for z in (-sz, sz) for y in (-sy, sy) for x in (-sx, sx)]
    faces = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    obj = mesh_object(name, verts, faces, parent=parent)
    obj.location = location
    obj.rotation_euler[2] = rot_z
    return obj


def cylinder(name: str, radius: float, z0: float, z1: float, location=(0.0, 0.0, 0.0), n: int = 64,
             parent=None) -> bpy.types.Object:
    """A closed cylinder about Z from height z0 to z1, smooth-shaded on its side."""
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = np.stack([radius * np.cos(a), radius * np.sin(a)], axis=1)
    verts = [(x, y, z0) for x, y in ring] + [(x, y, z1) for x, y in ring] + [(0, 0, z0), (0, 0, z1)]
    faces = [(i, (i + 1) % n, n + (i + 1) % n, n + i) for i in range(n)]
    faces += [((i + 1) % n, i, 2 * n) for i in range(n)]
    faces += [(n + i, n + (i + 1) % n, 2 * n + 1) for i in range(n)]
    obj = mesh_object(name, verts, faces, parent=parent)
    obj.data.polygons.foreach_set("use_smooth", [True] * n + [False] * (2 * n))
    obj.location = location
    return obj


PRIMITIVES = ("box", "cylinder", "cone", "sphere", "icosphere")
"""Shapes of `primitive`."""


def primitive(name: str, kind: str, size) -> bpy.types.Object:
    """A primitive of `kind` fitting a box of `size` (x, y, z), centred at the origin, smooth where round."""
    bm = bmesh.new()
    if kind == "box":
        bmesh.ops.create_cube(bm, size=1.0)
    elif kind in ("cylinder", "cone"):
        bmesh.ops.create_cone(bm, cap_ends=True, segments=32, radius1=0.5, radius2=0.5 if kind == "cylinder" else 0.0,
                              depth=1.0)
    elif kind == "sphere":
        bmesh.ops.create_uvsphere(bm, u_segments=32, v_segments=16, radius=0.5)
    elif kind == "icosphere":
        bmesh.ops.create_icosphere(bm, subdivisions=1, radius=0.5)
    else:
        raise ValueError(f"unknown primitive {kind!r}; known: {', '.join(PRIMITIVES)}")
    bmesh.ops.scale(bm, vec=tuple(float(s) for s in size), verts=bm.verts)
    mesh = bpy.data.meshes.new(name)
    bm.to_mesh(mesh)
    bm.free()
    if kind in ("cylinder", "cone", "sphere"):
        mesh.shade_smooth()
    return link(bpy.data.objects.new(name, mesh))


def load_model(directory: Path, name: str) -> bpy.types.Mesh:
    """The mesh (with its materials) of an n2d model directory, kept in memory for `instance()`.

    The model's OBJ is in metres in the object frame, Z up; the mesh keeps those coordinates.
    """
    before = set(bpy.data.objects)
    bpy.ops.wm.obj_import(filepath=str(directory / "mesh.obj"), forward_axis="Y", up_axis="Z")
    parts = [o for o in bpy.data.objects if o not in before]
    meshes = [o for o in parts if o.type == "MESH"]
    if len(meshes) != 1:
        raise ContractError(f"{directory / 'mesh.obj'} holds {len(meshes)} meshes, not one",
                            "give an n2d model directory (written by n2d reconstruct)")
    mesh = meshes[0].data
    mesh.name = f"model_{name}"
    mesh.use_fake_user = True  # survives clear_scene()
    for obj in parts:
        bpy.data.objects.remove(obj)
    return mesh


def instance(mesh: bpy.types.Mesh, name: str) -> bpy.types.Object:
    """A new object showing a loaded model's mesh (shared data, no copy)."""
    return link(bpy.data.objects.new(name, mesh))


def clear_scene(keep: tuple[bpy.types.Object, ...] = ()) -> None:
    """Remove every object but `keep`, then every data block no longer used (memory stays flat)."""
    for obj in list(bpy.data.objects):
        if obj not in keep:
            bpy.data.objects.remove(obj, do_unlink=True)
    bpy.data.orphans_purge(do_local_ids=True, do_linked_ids=True, do_recursive=True)
