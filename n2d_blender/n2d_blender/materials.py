"""Materials: Principled BSDF, image textures from arrays, and random procedural surfaces for domain randomisation."""

from __future__ import annotations

import bpy
import numpy as np


def principled(name: str, color, roughness: float = 0.5, specular: float = 0.5, metallic: float = 0.0):
    """A Principled BSDF material of linear `color`; returns (material, its node tree, the BSDF node)."""
    mat = bpy.data.materials.new(name)  # Blender 5 materials always have a node tree
    tree = mat.node_tree
    bsdf = tree.nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = (*color, 1.0)
    bsdf.inputs["Roughness"].default_value = roughness
    bsdf.inputs["Specular IOR Level"].default_value = specular
    bsdf.inputs["Metallic"].default_value = metallic
    return mat, tree, bsdf


def assign(obj: bpy.types.Object, mat: bpy.types.Material) -> None:
    """Give `obj` the single material `mat`."""
    obj.data.materials.clear()
    obj.data.materials.append(mat)


def image(name: str, rgb: np.ndarray) -> bpy.types.Image:
    """A packed-in-memory sRGB image from an HxWx3 (or HxW) uint8 array, row 0 at the top."""
    if rgb.ndim == 2:
        rgb = np.repeat(rgb[:, :, None], 3, axis=2)
    h, w = rgb.shape[:2]
    img = bpy.data.images.new(name, w, h, alpha=False)
    rgba = np.concatenate([rgb, np.full((h, w, 1), 255, np.uint8)], axis=2)[::-1]
    img.pixels.foreach_set((rgba.astype(np.float32) / 255).ravel())
    img.pack()
    return img


def textured(name: str, img: bpy.types.Image, roughness: float = 0.5, specular: float = 0.5,
             interpolation: str = "Linear", coords: str = "UV", scale: float = 1.0) -> bpy.types.Material:
    """A material whose base colour is `img`, mapped by UV (or by object coordinates times `scale`, repeated)."""
    mat, tree, bsdf = principled(name, (1.0, 1.0, 1.0), roughness, specular)
    tex = tree.nodes.new("ShaderNodeTexImage")
    tex.image = img
    tex.interpolation = interpolation
    tex.extension = "EXTEND" if coords == "UV" else "REPEAT"
    if coords != "UV":
        coord, mapping = tree.nodes.new("ShaderNodeTexCoord"), tree.nodes.new("ShaderNodeMapping")
        mapping.inputs["Scale"].default_value = (scale, scale, scale)
        tree.links.new(coord.outputs["Object"], mapping.inputs["Vector"])
        tree.links.new(mapping.outputs["Vector"], tex.inputs["Vector"])
    tree.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
    return mat


def pattern(name: str, kind: str, color_a, color_b, scale: float, roughness: float, specular: float = 0.5):
    """A procedural surface between two linear colours: noise, voronoi, wave, magic, checker or brick."""
    mat, tree, bsdf = principled(name, color_a, roughness=roughness, specular=specular)
    nodes, links = tree.nodes, tree.links
    coord = nodes.new("ShaderNodeTexCoord")
    tex = nodes.new(PATTERNS[kind])
    tex.inputs["Scale"].default_value = scale
    links.new(coord.outputs["Object"], tex.inputs["Vector"])
    if kind in ("checker", "brick"):
        tex.inputs["Color1"].default_value = (*color_a, 1.0)
        tex.inputs["Color2"].default_value = (*color_b, 1.0)
        links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
    else:
        mix = nodes.new("ShaderNodeMix")
        mix.data_type = "RGBA"
        mix.inputs["A"].default_value = (*color_a, 1.0)
        mix.inputs["B"].default_value = (*color_b, 1.0)
        links.new(tex.outputs["Distance" if kind == "voronoi" else "Fac"], mix.inputs["Factor"])
        links.new(mix.outputs["Result"], bsdf.inputs["Base Color"])
    return mat, tree, bsdf


PATTERNS = {"noise": "ShaderNodeTexNoise", "voronoi": "ShaderNodeTexVoronoi", "wave": "ShaderNodeTexWave",
            "magic": "ShaderNodeTexMagic", "checker": "ShaderNodeTexChecker", "brick": "ShaderNodeTexBrick"}
"""Blender's procedural textures used by `pattern`."""


