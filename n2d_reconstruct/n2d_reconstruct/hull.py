"""The fast CPU path's geometry: the visual hull of the masks as a signed distance field.

Each view contributes the signed distance of a point's projection to that view's silhouette
boundary (pixels, positive inside the mask), scaled by depth / focal length to metres: the distance
to the view's silhouette cone, to first order. The hull is the intersection of all cones, so its
field is the smallest of these, or the (k+1)-th smallest to forgive k views whose mask missed a
part of the object. Points below the plate surface are outside (the object stands on it). The field
is continuous, so marching cubes places the surface to a fraction of a voxel.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import torch
import trimesh

from n2d_reconstruct.data import Views

OUTSIDE_IMAGE_PX = -1e4
"""Signed distance given to points that project outside a view: carved away, as every view is expected to
see the whole object (a part outside one view's frame is lost)."""


@dataclass
class HullConfig:
    """The visual hull (fast path)."""

    forgive_views: int = 0
    """A point outside the masks of this many views is still kept (robustness to a few bad masks)."""
    plate_clearance_m: float = 0.0
    """Height above the plate surface where the object starts; everything below is cut away, metres."""
    search_height_m: float = 0.5
    """Height above the plate searched for the object, metres."""
    slack_px: float = 0.25
    """The mesh is pulled back where it stands further than this outside the hull, in pixels at the object's
    distance (a binary mask places the outline to about half a pixel, so the hull cuts that far into flat faces);
    negative: never."""
    pull_forgive_px: float = 0.75
    """The pull back (slack_px) and the fast path's hull forgive the one view whose mask alone cuts deeper than
    this into the surface than the next view's does, in pixels at the object's distance: a segmented mask that
    misses a sliver of the object (a side seen nearly edge-on, a few pixels wide and close in colour to what lies
    behind it) notches the hull in that view alone, and the surface would be pulled into the notch, or the fast
    path's refinement start from it (captured box: a dent 3 mm deep where one view's mask missed 1-2 pixels).
    Exact masks agree to a fraction of a pixel and keep the whole hull; negative: never forgive."""

    def __post_init__(self):
        if self.forgive_views < 0:
            raise ValueError("forgive_views must be >= 0")
        if self.search_height_m <= 0:
            raise ValueError("search_height_m must be > 0")
        if not np.isfinite(self.slack_px):
            raise ValueError("slack_px must be a number of pixels (negative: never pull the mesh back)")


class VisualHull:
    """Signed distance (metres, negative inside) to the visual hull of `views` above the plate.

    `plates`: P x 4 planes (unit normal n, offset d) above which the object stands, n . p + d >= clearance; default
    the turntable plate, z >= clearance. A session of several placements has one plate per placement, each in the
    first placement's frame: each cuts away only what lies below its own plate."""

    def __init__(self, views: Views, cfg: HullConfig, plates: np.ndarray | None = None):
        if cfg.forgive_views >= len(views):
            raise ValueError(f"forgive_views ({cfg.forgive_views}) must be smaller than the number of views "
                             f"({len(views)})")
        self.cfg = cfg
        self.K = torch.as_tensor(views.K, dtype=torch.float64)
        T_cam_turntable = np.linalg.inv(views.T_turntable_cam)
        self.R = torch.as_tensor(T_cam_turntable[:, :3, :3], dtype=torch.float64)
        self.t = torch.as_tensor(T_cam_turntable[:, :3, 3], dtype=torch.float64)
        self.size = torch.tensor([views.width, views.height], dtype=torch.float64)
        self.dist = torch.as_tensor(np.stack([signed_distance_px(m) for m in views.masks]))[:, None]
        self.pixel_m = views.pixel_m
        """The size of a pixel at the turntable centre, metres."""
        self.plates = torch.as_tensor(np.array([[0.0, 0.0, 1.0, 0.0]]) if plates is None else plates,
                                      dtype=torch.float64)

    def __call__(self, points: np.ndarray, chunk: int = 1 << 17, forgive_views: int | None = None) -> np.ndarray:
        """N x 3 turntable-frame points -> N signed distances, metres (negative inside); `forgive_views`
        overrides the config's."""
        k = self.cfg.forgive_views if forgive_views is None else forgive_views
        out = np.empty(len(points))
        for s in range(0, len(points), chunk):
            out[s:s + chunk] = self._chunk(torch.as_tensor(points[s:s + chunk], dtype=torch.float64), k).numpy()
        return out

    def below_plates(self, points: np.ndarray) -> np.ndarray:
        """The signed distance (metres) of N x 3 points to the space above every plate: positive below any of
        them (where no object stood), the cut the hull itself makes."""
        planes = self.plates.numpy()
        return self.cfg.plate_clearance_m - (points @ planes[:, :3].T + planes[:, 3]).min(axis=1)

    def lenient(self, points: np.ndarray, notch_m: float) -> np.ndarray:
        """Signed distances (metres) that forgive one more view where that view alone puts a point more than
        `notch_m` further outside than the next view does (a notch in one mask); the hull itself when no view is
        left to forgive."""
        strict = self(points)
        if self.cfg.forgive_views + 1 >= len(self.R):
            return strict
        forgiving = self(points, forgive_views=self.cfg.forgive_views + 1)
        return np.where(strict - forgiving > notch_m, forgiving, strict)

    def _chunk(self, p: torch.Tensor, k: int) -> torch.Tensor:
        cam = torch.einsum("vij,nj->vni", self.R, p) + self.t[:, None]          # V x N x 3
        z = cam[..., 2].clamp_min(1e-6)
        uv = torch.stack([self.K[0, 0] * cam[..., 0] / z + self.K[0, 2],
                          self.K[1, 1] * cam[..., 1] / z + self.K[1, 2]], dim=-1)
        # grid_sample's align_corners=True maps -1 and 1 to the centres of the first and last pixel.
        grid = (2 * uv / (self.size - 1) - 1).float()[:, :, None]                 # V x N x 1 x 2
        d = torch.nn.functional.grid_sample(self.dist, grid, align_corners=True, padding_mode="border")[:, 0, :, 0]
        outside = (uv < -0.5).any(-1) | (uv > self.size - 0.5).any(-1) | (cam[..., 2] <= 0)
        d = torch.where(outside, torch.full_like(d, OUTSIDE_IMAGE_PX), d.double())
        metric = d * z / self.K[0, 0]
        inside = metric.kthvalue(k + 1, dim=0).values if k else metric.min(dim=0).values
        above = (p @ self.plates[:, :3].T + self.plates[:, 3]).min(dim=1).values - self.cfg.plate_clearance_m
        return -torch.minimum(inside, above)


def pull_inside(mesh: trimesh.Trimesh, hull: Callable[[np.ndarray], np.ndarray], slack_m: float,
                iterations: int = 6) -> tuple[trimesh.Trimesh, dict]:
    """`mesh` with every vertex that stands more than `slack_m` outside `hull` (a signed distance, e.g. a
    `VisualHull` or its `lenient`) moved back to that distance along its normal, and what moved (fraction of
    the vertices, largest move in mm).

    The object lies inside every silhouette cone, so a surface outside the hull is an error: NeuS rounds
    corners out and leaves broad bumps where no texture pins the depth. The hull's field is a distance to
    first order only, hence a few passes. A step is taken only where it brings the vertex closer to the hull:
    the normal of a folded face points the wrong way, and following it would push the vertex further out.
    """
    vertices = mesh.vertices.copy()
    normals = mesh.vertex_normals
    distance = hull(vertices)
    for _ in range(iterations):
        over = np.maximum(distance - slack_m, 0.0)
        stepped = vertices - normals * over[:, None]
        closer = hull(stepped)
        better = (over > 0) & (closer < distance)
        vertices[better], distance[better] = stepped[better], closer[better]
    moved = np.linalg.norm(vertices - mesh.vertices, axis=1)
    stats = {"moved_fraction": round(float(np.mean(moved > 0)), 4),
             "max_move_mm": round(float(moved.max(initial=0.0)) * 1000, 3), "slack_mm": round(slack_m * 1000, 3)}
    return trimesh.Trimesh(vertices, mesh.faces, process=False), stats


def signed_distance_px(mask: np.ndarray) -> np.ndarray:
    """H x W float32 signed distance of each pixel centre to the mask's boundary (pixel edges), positive
    inside the mask, in pixels."""
    m = mask.astype(np.uint8)
    inside = cv2.distanceTransform(m, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    outside = cv2.distanceTransform(1 - m, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return np.where(m > 0, inside - 0.5, 0.5 - outside).astype(np.float32)


def search_box(radius_m: float, cfg: HullConfig) -> np.ndarray:
    """2 x 3 [min, max] turntable-frame box the object is searched in: over the plate, up to search_height_m."""
    return np.array([[-radius_m, -radius_m, cfg.plate_clearance_m], [radius_m, radius_m, cfg.search_height_m]])
