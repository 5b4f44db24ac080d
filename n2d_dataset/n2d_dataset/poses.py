"""Pose sampling for scenes, in plain numpy: camera placement around a target and random rotations.

World frame: Z up, the floor at z = 0. Camera poses are `T_world_cam` of the OpenCV camera frame.
"""

from __future__ import annotations

import numpy as np

from n2d_common.frames import R_from_quat, make_T, project


def look_at(eye, target, roll_rad: float = 0.0) -> np.ndarray:
    """T_world_cam of an OpenCV camera at `eye` looking at `target` (image up towards world +Z), rolled about
    its optical axis by `roll_rad`."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    z /= np.linalg.norm(z)
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.999 else np.array([0.0, 1.0, 0.0])
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    c, s = np.cos(roll_rad), np.sin(roll_rad)
    x, y = c * x + s * y, -s * x + c * y
    return make_T(np.stack([x, y, z], axis=1), eye)


def sample_camera(rng: np.random.Generator, target, distance_m: tuple[float, float],
                  elevation_deg: tuple[float, float], jitter_m: float, roll_deg: float) -> np.ndarray:
    """A random T_world_cam looking at `target` (moved by up to `jitter_m` per axis) from a distance and
    elevation in the given ranges, from any azimuth, rolled by up to +-`roll_deg`."""
    look = np.asarray(target, float) + rng.uniform(-jitter_m, jitter_m, 3)
    d = rng.uniform(*distance_m)
    el, az = np.radians(rng.uniform(*elevation_deg)), rng.uniform(0, 2 * np.pi)
    eye = look + d * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    return look_at(eye, look, np.radians(rng.uniform(-roll_deg, roll_deg)))


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A uniformly random 3x3 rotation (Shoemake's method)."""
    u1, u2, u3 = rng.random(3)
    q = np.array([np.sqrt(1 - u1) * np.sin(2 * np.pi * u2), np.sqrt(1 - u1) * np.cos(2 * np.pi * u2),
                  np.sqrt(u1) * np.sin(2 * np.pi * u3), np.sqrt(u1) * np.cos(2 * np.pi * u3)])
    return R_from_quat(q)


def in_view(K: np.ndarray, width: int, height: int, T_cam_obj: np.ndarray) -> bool:
    """Whether an object's origin projects into the image, in front of the camera."""
    (u, v), = project(K, T_cam_obj, np.zeros((1, 3)))
    return T_cam_obj[2, 3] > 0 and 0 <= u < width and 0 <= v < height
