"""Lighting: random lights of random colour temperature, and a gradient sky around the scene."""

from __future__ import annotations

import bpy
import numpy as np
from mathutils import Vector

from n2d_blender.objects import link
from n2d_common.images import kelvin_to_rgb, random_color


def light(name: str, kind: str, power_w: float, location, target, color=(1.0, 1.0, 1.0),
          size_m: float = 0.3) -> bpy.types.Object:
    """A light of `kind` (POINT, SPOT, AREA, SUN) at `location`, pointed at `target` (spot, area, sun)."""
    data = bpy.data.lights.new(name, type=kind)
    data.color = color
    data.energy = power_w
    if kind == "AREA":
        data.size = size_m
    elif kind in ("POINT", "SPOT"):
        data.shadow_soft_size = size_m / 4
    if kind == "SPOT":
        data.spot_size = np.radians(60.0)
        data.spot_blend = 0.5
    obj = link(bpy.data.objects.new(name, data))
    obj.location = location
    obj.rotation_euler = (Vector(target) - Vector(location)).to_track_quat("-Z", "Y").to_euler()
    return obj


def random_lights(rng: np.random.Generator, count: int, power_w: tuple[float, float], target) -> None:
    """`count` lights of random type, colour temperature (2700-7500 K) and power above `target`."""
    for i in range(count):
        kind = str(rng.choice(["POINT", "SPOT", "AREA", "SUN"], p=[0.35, 0.2, 0.35, 0.1]))
        azimuth, elevation = rng.uniform(0, 2 * np.pi), rng.uniform(np.radians(25), np.radians(85))
        distance = rng.uniform(0.8, 2.5)
        location = np.asarray(target) + distance * np.array(
            [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
        power = rng.uniform(*power_w) * distance ** 2  # similar irradiance at the target whatever the distance
        if kind == "SUN":
            power = rng.uniform(1.0, 5.0)  # W/m^2
        light(f"light{i}", kind, power, location, target, kelvin_to_rgb(rng.uniform(2700, 7500)),
              size_m=rng.uniform(0.1, 1.0))


def gradient_world(rng: np.random.Generator, strength: float) -> None:
    """A sky graded from a random horizon colour to a random zenith colour, lighting from all around."""
    world = bpy.context.scene.world or bpy.data.worlds.new("world")
    bpy.context.scene.world = world
    tree = world.node_tree
    nodes, links = tree.nodes, tree.links
    for node in [n for n in nodes if n.type not in ("BACKGROUND", "OUTPUT_WORLD")]:
        nodes.remove(node)
    background = nodes["Background"]
    coord = nodes.new("ShaderNodeTexCoord")
    split = nodes.new("ShaderNodeSeparateXYZ")
    ramp = nodes.new("ShaderNodeValToRGB")
    ramp.color_ramp.elements[0].position = 0.4
    ramp.color_ramp.elements[0].color = (*random_color(rng), 1.0)
    ramp.color_ramp.elements[1].color = (*random_color(rng), 1.0)
    remap = nodes.new("ShaderNodeMapRange")
    remap.inputs["From Min"].default_value = -1.0
    links.new(coord.outputs["Generated"], split.inputs["Vector"])
    links.new(split.outputs["Z"], remap.inputs["Value"])
    links.new(remap.outputs["Result"], ramp.inputs["Fac"])
    links.new(ramp.outputs["Color"], background.inputs["Color"])
    background.inputs["Strength"].default_value = strength
