"""Physics: drop objects with Blender's rigid-body simulation so they come to rest naturally."""

from __future__ import annotations

import bpy
import numpy as np
from mathutils import Matrix


def drop(active: list[bpy.types.Object], passive: list[bpy.types.Object], steps: int = 90,
         friction: float = 0.8) -> None:
    """Simulate `active` objects falling onto `passive` ones for `steps` frames (24 fps), then fix each
    object's resting pose in place and remove the simulation (renders no longer depend on its cache).

    Collision shapes are convex hulls: fast and stable; a concave object rests as its hull would.
    """
    scene = bpy.context.scene
    if scene.rigidbody_world is not None:
        bpy.ops.rigidbody.world_remove()
    bpy.ops.rigidbody.world_add()
    world = scene.rigidbody_world
    world.collection = bpy.data.collections.new("rigid_bodies")
    world.point_cache.frame_start, world.point_cache.frame_end = 1, steps
    world.substeps_per_frame, world.solver_iterations = 10, 10
    for obj in passive + active:
        world.collection.objects.link(obj)
        bpy.context.view_layer.objects.active = obj
        bpy.ops.rigidbody.object_add()
        body = obj.rigid_body
        body.type = "ACTIVE" if obj in active else "PASSIVE"
        body.collision_shape = "CONVEX_HULL" if obj in active else "MESH"
        body.friction = friction
        body.linear_damping, body.angular_damping = 0.2, 0.3
        body.collision_margin = 0.0005
    for frame in range(1, steps + 1):
        scene.frame_set(frame)
    rest = {obj: np.array(obj.matrix_world) for obj in active}
    bpy.ops.rigidbody.world_remove()
    scene.frame_set(1)
    for obj, T in rest.items():
        obj.matrix_world = Matrix(T.tolist())
