"""How objects rest on a table: the stable resting poses of a mesh, and the orientation a scene gives a model.

Plain numpy and trimesh (no bpy), shared by both renderers. A resting pose is a face of the mesh's convex hull
(coplanar hull triangles merged) that the centre of mass projects into, as a rigid body released on a table
settles on one of them; its probability is the solid angle the face subtends from the centre of mass (the
quasi-static model of Wiegley et al. and of trimesh's `compute_stable_poses`, without its sampling). The model
frame's Z up is how the object stood on the turntable, a stable pose the capture has seen.

Orientations are 3 x 3 rotations R_world_obj whose lowest point lies on the plane z = 0 once shifted by
`rest_height`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from n2d_common.frames import rot_z
from n2d_dataset.poses import random_rotation

MIN_PROBABILITY = 0.005
"""Resting poses less likely than this are left out (slivers of the hull an object never settles on)."""
COPLANAR_COS = np.cos(np.radians(2.0))
"""Hull triangles whose normals are within 2 degrees of each other form one resting face."""


@dataclass(frozen=True)
class RestingPose:
    """One way a model rests on a table."""

    R: np.ndarray
    """3 x 3 rotation from the object frame to a frame with Z up and the resting face down."""
    probability: float
    """Fraction of random drops expected to end in this pose (the face's solid angle over 4 pi)."""


def _inside_triangles(p: np.ndarray, tri: np.ndarray) -> bool:
    """Whether point p (3,) lies in any of the coplanar triangles tri (T x 3 x 3), tested in their plane."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    n = np.cross(b - a, c - a)
    sides = [np.einsum("ij,ij->i", np.cross(q - o, p - o), n) for o, q in ((a, b), (b, c), (c, a))]
    return bool(np.any((sides[0] >= 0) & (sides[1] >= 0) & (sides[2] >= 0)))


def _solid_angle(p: np.ndarray, tri: np.ndarray) -> float:
    """Solid angle subtended at p by triangles tri (T x 3 x 3), steradians (Van Oosterom and Strackee)."""
    r = tri - p
    lengths = np.linalg.norm(r, axis=2)
    a, b, c = r[:, 0], r[:, 1], r[:, 2]
    la, lb, lc = lengths.T
    numerator = np.abs(np.einsum("ij,ij->i", a, np.cross(b, c)))
    denominator = (la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", a, c) * lb
                   + np.einsum("ij,ij->i", b, c) * la)
    return float(np.sum(2 * np.arctan2(numerator, denominator)))


def _down_rotation(n: np.ndarray) -> np.ndarray:
    """A rotation taking unit vector n to -Z (the face with outward normal n then faces the table)."""
    target = np.array([0.0, 0.0, -1.0])
    v, c = np.cross(n, target), float(np.dot(n, target))
    if c < -1 + 1e-9:  # n is +Z: turn half a turn about X
        return np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)


def resting_poses(mesh: trimesh.Trimesh, min_probability: float = MIN_PROBABILITY) -> list[RestingPose]:
    """The stable resting poses of `mesh` (object frame, metres), most likely first.

    The centre of mass is the volume's when the mesh is watertight, else the hull's."""
    hull = mesh.convex_hull
    com = mesh.center_mass if mesh.is_watertight and mesh.volume > 0 else hull.center_mass
    normals, tris = hull.face_normals, hull.triangles
    unused = np.ones(len(normals), bool)
    poses = []
    for i in np.argsort(-hull.area_faces):
        if not unused[i]:
            continue
        group = unused & (normals @ normals[i] > COPLANAR_COS)
        unused &= ~group
        n = normals[group].mean(axis=0)
        n /= np.linalg.norm(n)
        plane_point = tris[i, 0]
        foot = com - np.dot(com - plane_point, n) * n
        if not _inside_triangles(foot, tris[group]):
            continue
        poses.append(RestingPose(_down_rotation(n), _solid_angle(com, tris[group]) / (4 * np.pi)))
    total = sum(p.probability for p in poses) or 1.0
    poses = [RestingPose(p.R, p.probability / total) for p in poses]
    kept = [p for p in poses if p.probability >= min_probability] or poses[:1]
    total = sum(p.probability for p in kept)
    return sorted((RestingPose(p.R, p.probability / total) for p in kept), key=lambda p: -p.probability)


def rest_height(vertices: np.ndarray, R: np.ndarray) -> float:
    """Height of the object origin above the table when the object rests with rotation R (metres)."""
    return float(-(vertices @ R.T)[:, 2].min())


def sample_orientation(rng: np.random.Generator, poses: list[RestingPose], upright: float, resting: float
                       ) -> tuple[np.ndarray, str]:
    """A world rotation for a model on a table, and how it was drawn ("upright", "resting" or "random").

    With probability `upright` the model stands as it was captured (Z up), with `resting` it lies in one of its
    resting poses drawn by probability, otherwise it gets a uniformly random rotation (physics settles it, or it
    floats); each about a random yaw."""
    u = rng.random()
    yaw = rot_z(rng.uniform(0, 2 * np.pi))[:3, :3]
    if u < upright:
        return yaw, "upright"
    if u < upright + resting and poses:
        k = rng.choice(len(poses), p=np.array([p.probability for p in poses]))
        return yaw @ poses[k].R, "resting"
    return random_rotation(rng), "random"
