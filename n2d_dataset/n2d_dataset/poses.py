"""Pose sampling for scenes, in plain numpy: camera placement around a target and random rotations.

World frame: Z up, the floor at z = 0. Camera poses are `T_world_cam` of the OpenCV camera frame.

A model's frame has Z up as the object stood on the turntable. A model from one placement is open: the capture
never saw the side it stood on, so the mesh is cut at the plate there, and no frame shows it from below that cut.
A closed model (fused from two placements, or a simulator's whole mesh) is shown from every side: its in-hand
frames also draw the camera from below the held object (elevations down to minus `elevation_deg`'s upper end).
"""

from __future__ import annotations

import numpy as np

from n2d_common.frames import R_from_quat, inv_T, make_T, project


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


def view_elevation_deg(T_cam_obj: np.ndarray) -> float:
    """Elevation of the camera seen from the object's origin, in the object's frame, degrees (negative: from
    below, the side the object stood on in the capture)."""
    eye = inv_T(T_cam_obj)[:3, 3]
    return float(np.degrees(np.arcsin(eye[2] / max(float(np.linalg.norm(eye)), 1e-12))))


def elevation_range(elevation_deg: tuple[float, float], closed: bool, in_hand: bool) -> tuple[float, float]:
    """The camera elevations (degrees, seen from the target) a frame draws from: the config's, or for an in-hand
    frame of a closed model the whole band from below to above the held object."""
    return (-elevation_deg[1], elevation_deg[1]) if closed and in_hand else tuple(elevation_deg)


def candidate_camera(rng: np.random.Generator, camera, model, T_world_obj: np.ndarray,
                     in_hand: bool) -> np.ndarray | None:
    """A random T_world_cam looking at a frame's target (`camera`: the dataset's CameraConfig; `model`: the target's
    Model), or None where it misses: the target's origin out of the image, or an open model seen from below the
    plane of its base (its cut)."""
    T_world_cam = sample_camera(rng, T_world_obj[:3, 3], camera.distance_m,
                                elevation_range(camera.elevation_deg, model.closed, in_hand), camera.look_at_jitter_m,
                                camera.roll_deg)
    T_cam_obj = inv_T(T_world_cam) @ T_world_obj
    if not in_view(camera.K(), camera.width, camera.height, T_cam_obj):
        return None
    if not model.closed and inv_T(T_cam_obj)[2, 3] < model.min_m[2]:
        return None
    return T_world_cam
