"""The sparse viewpoint model of an object: its silhouette contour seen from many directions, as 3D points and
outward normals in the object frame (the representation the region-based trackers of Stoiber et al., RBOT and
SRT3D, precompute so that no rendering is needed while refining or tracking).

`build_region_model(vertices, faces)` renders the mesh's silhouette from `views` directions spread evenly over the
sphere (a Fibonacci lattice), walks each silhouette's outer contour and keeps `points` evenly spaced contour
points: where the surface meets the silhouette edge (the boundary pixel's centre moved half a pixel outwards, at
the depth the rasterizer gave it) and the contour's outward normal, both lifted back into the object frame.
`RegionModel.view(T_cam_obj)` returns the stored view nearest to the direction a camera sees the object from.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from n2d_common.contracts import atomic_write_bytes
from n2d_common.errors import ContractError
from n2d_common.frames import inv_T, transform_points
from n2d_common.raster import rasterize
from n2d_common.torch_utils import torch_threads

VIEWS = 1000
"""Directions of the sparse model: neighbours about 6.5 degrees apart."""
POINTS = 200
"""Contour points per direction."""
IMAGE_PX = 256
"""Side of the square silhouette renders; the object's bounding sphere spans 90 % of it."""
RENDER_FACES = 5000
"""Meshes with more faces are decimated to this many for the silhouette renders (a reconstructed model's 40k
faces would cost seconds per view; at 256 px the decimated silhouette is the same to a fraction of a pixel)."""
_FOCAL = 1000.0
REGION_MODEL = "region_model.npz"
"""File name of a cached sparse viewpoint model."""


@dataclass
class RegionModel:
    """Contour points and normals of an object seen from `len(directions)` directions (object frame, metres)."""

    directions: np.ndarray
    """N x 3 unit vectors from the centre towards the camera, object frame."""
    points: np.ndarray
    """N x P x 3 contour points, object frame, metres."""
    normals: np.ndarray
    """N x P x 3 unit outward normals of the contour (perpendicular to the viewing ray), object frame."""
    centre: np.ndarray
    """3: centre of the object's bounding box (the directions point away from it)."""
    radius: float
    """Bounding-sphere radius about `centre`, metres."""
    key: str = ""
    """Hash of the mesh it was built from (a cache of another mesh is built again)."""

    def view(self, T_cam_obj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(P x 3 points, P x 3 normals) of the stored view nearest to how the camera sees the object."""
        camera = inv_T(T_cam_obj)[:3, 3] - self.centre
        i = int(np.argmax(self.directions @ (camera / (np.linalg.norm(camera) + 1e-12))))
        return self.points[i], self.normals[i]

    def save(self, path: Path) -> None:
        """Write as .npz (atomically)."""
        import io

        buf = io.BytesIO()
        np.savez_compressed(buf, directions=self.directions, points=self.points, normals=self.normals,
                            centre=self.centre, radius=np.array(self.radius), key=np.array(self.key))
        atomic_write_bytes(Path(path), buf.getvalue())

    @classmethod
    def load(cls, path: Path) -> RegionModel:
        with np.load(path) as z:
            return cls(z["directions"], z["points"], z["normals"], z["centre"], float(z["radius"]), str(z["key"]))


def fibonacci_sphere(n: int) -> np.ndarray:
    """n x 3 unit vectors spread evenly over the sphere."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (1.0 + 5 ** 0.5) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


def look_from(direction: np.ndarray, centre: np.ndarray, distance: float) -> np.ndarray:
    """T_cam_obj of an OpenCV camera `distance` from `centre` along `direction` (object frame), looking at it."""
    z = -direction / np.linalg.norm(direction)
    up = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R_obj_cam = np.stack([x, y, z], 1)
    T = np.eye(4)
    T[:3, :3] = R_obj_cam.T
    T[:3, 3] = -R_obj_cam.T @ (centre + distance * direction / np.linalg.norm(direction))
    return T


def decimated(vertices: np.ndarray, faces: np.ndarray, count: int = RENDER_FACES) -> tuple[np.ndarray, np.ndarray]:
    """The mesh with at most `count` faces (decimated where it has more), as float64 vertices and int64 faces."""
    V, F = np.asarray(vertices, float), np.asarray(faces, np.int64).reshape(-1, 3)
    if len(F) > count:
        import fast_simplification

        V, F = fast_simplification.simplify(V.astype(np.float32), F, target_count=count)
        V, F = np.asarray(V, float), np.asarray(F, np.int64)
    return V, F


def build_region_model(vertices: np.ndarray, faces: np.ndarray, views: int = VIEWS, points: int = POINTS,
                       image_px: int = IMAGE_PX) -> RegionModel:
    """The sparse viewpoint model of a mesh (V x 3 object-frame vertices in metres, F x 3 faces)."""
    V = np.asarray(vertices, float)
    F = np.asarray(faces, np.int64).reshape(-1, 3)
    if len(V) == 0 or len(F) == 0 or not np.isfinite(V).all():
        raise ContractError("the model has no faces or non-finite vertices", "check the model's mesh.obj")
    centre = 0.5 * (V.min(0) + V.max(0))
    radius = float(np.linalg.norm(V - centre, axis=1).max())
    if not radius > 0:
        raise ContractError("the model is a single point", "check the model's mesh.obj")
    V, F = decimated(V, F)
    distance = _FOCAL * radius / (0.45 * image_px)
    c = (image_px - 1) / 2.0
    K = np.array([[_FOCAL, 0.0, c], [0.0, _FOCAL, c], [0.0, 0.0, 1.0]])
    K_inv = np.linalg.inv(K)
    dirs = fibonacci_sphere(views)
    all_points = np.zeros((views, points, 3))
    all_normals = np.zeros((views, points, 3))
    with torch_threads(1):
        for i, d in enumerate(dirs):
            all_points[i], all_normals[i] = _view(V, F, K, K_inv, look_from(d, centre, distance), image_px, points)
    return RegionModel(dirs, all_points, all_normals, centre, radius)


def _view(V: np.ndarray, F: np.ndarray, K: np.ndarray, K_inv: np.ndarray, T: np.ndarray, image_px: int,
          points: int) -> tuple[np.ndarray, np.ndarray]:
    """Contour points and normals (object frame) of the mesh's silhouette seen with pose T."""
    r = rasterize(transform_points(T, V), F, K, image_px, image_px)
    px, normal = contour_samples(r.mask, points)
    depth = r.depth[px[:, 1], px[:, 0]]
    edge = px + 0.5 * normal  # the silhouette edge lies half a pixel outside the boundary pixel's centre
    cam = (np.c_[edge, np.ones(len(edge))] @ K_inv.T) * depth[:, None]
    R_obj_cam = T[:3, :3].T
    return (cam - T[:3, 3]) @ R_obj_cam.T, np.c_[normal, np.zeros(len(normal))] @ R_obj_cam.T


def contour_samples(mask: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """`count` boundary pixels (x, y ints) evenly spaced along a mask's outer contours, and their unit outward
    normals (count x 2, image x right, y down): the direction in which the mask, blurred over a few pixels,
    falls fastest (the staircase of pixel contours would tilt normals taken from neighbouring contour pixels)."""
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    contours = [c[:, 0] for c in contours if len(c) >= 8]
    if not contours:
        raise ContractError("the model's silhouette is empty from some direction", "check the model's mesh.obj")
    lengths = np.array([len(c) for c in contours], float)
    share = np.maximum(1, np.round(count * lengths / lengths.sum()).astype(int))
    share[np.argmax(share)] += count - share.sum()
    pixels = np.concatenate([c[np.linspace(0, len(c), int(n), endpoint=False).astype(int)]
                             for c, n in zip(contours, share) if n > 0])[:count]
    sigma = max(1.0, mask.shape[0] / 128)
    blurred = cv2.GaussianBlur(mask.astype(np.float32), (0, 0), sigma)
    gx = cv2.Sobel(blurred, cv2.CV_32F, 1, 0, ksize=3)[pixels[:, 1], pixels[:, 0]]
    gy = cv2.Sobel(blurred, cv2.CV_32F, 0, 1, ksize=3)[pixels[:, 1], pixels[:, 0]]
    normal = -np.stack([gx, gy], 1).astype(np.float64)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True) + 1e-12
    return pixels.astype(int), normal
