"""Camera: a Blender camera with exact OpenCV intrinsics, posed and read back in OpenCV's axes.

Blender's camera looks down its -Z with Y up; OpenCV's looks down +Z with Y down. With sensor fit
HORIZONTAL, a 36 mm sensor and lens = fx * 36 / W, the image has fx = fy and its principal point at
((W-1)/2, (H-1)/2) in OpenCV's pixel-centre convention (Blender's pixel i covers [i, i+1]).
"""

from __future__ import annotations

import bpy
import numpy as np
from mathutils import Matrix

from n2d_blender.objects import link

BL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])
"""Flips between OpenCV's and Blender's camera axes (its own inverse)."""


def make_camera(width: int, height: int, focal_px: float) -> bpy.types.Object:
    """The scene camera with square pixels of focal length `focal_px` and a centred principal point."""
    scene = bpy.context.scene
    data = bpy.data.cameras.new("camera")
    data.sensor_fit = "HORIZONTAL"
    data.sensor_width = 36.0
    data.lens = focal_px * data.sensor_width / width
    data.clip_start, data.clip_end = 0.01, 50.0
    cam = link(bpy.data.objects.new("camera", data))
    scene.camera = cam
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    scene.render.pixel_aspect_x = scene.render.pixel_aspect_y = 1.0
    return cam


def set_pose(cam: bpy.types.Object, T_world_cam: np.ndarray) -> None:
    """Place the camera at `T_world_cam`, a 4x4 pose of the OpenCV camera frame in the world."""
    cam.matrix_world = Matrix((T_world_cam @ BL_FROM_CV).tolist())


def world_pose(obj: bpy.types.Object) -> np.ndarray:
    """4x4 T_world_obj of a Blender object (as posed now; scale must be 1)."""
    return np.array(obj.matrix_world)
