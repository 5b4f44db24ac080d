"""Texture points followed from one frame to the next by optical flow: the texture term of tracking.

A silhouette pins the pose only through the object's outline: rotations that barely move the outline (a box
turning about an axis through its faces, seen face on) are weakly held, and frame-to-frame the pose wobbles by a
few tenths of a degree. Points of the object's own texture hold them. After each tracked frame `FlowPoints.select`
picks corners (Shi-Tomasi) inside the projected silhouette, away from its edge, and lifts them onto the model
through a depth render at the frame's pose (object-frame points). In the next frame `follow` moves them with
pyramidal Lucas-Kanade flow, forward and back; a point that does not come back within `fb_px` (occluded by a
finger, on a highlight, past the border) is dropped. The pairs of object-frame points and observed pixels go into
`refine_pose` as a reprojection term beside the contour lines, which keep the pose from drifting.
"""

from __future__ import annotations

import cv2
import numpy as np

from n2d_common.frames import inv_T, transform_points
from n2d_common.raster import render_depth
from n2d_common.torch_utils import torch_threads
from n2d_dope.config import FlowConfig
from n2d_dope.region_model import decimated


class FlowPoints:
    """The texture points of one tracked object between consecutive frames."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, cfg: FlowConfig | None = None):
        self.cfg = cfg or FlowConfig()
        self.vertices, self.faces = decimated(vertices, faces)
        self.reset()

    def reset(self) -> None:
        """Forget the points (the next frame has no texture term)."""
        self._gray: np.ndarray | None = None
        self._px = np.zeros((0, 1, 2), np.float32)
        self._X = np.zeros((0, 3))

    def select(self, gray: np.ndarray, K: np.ndarray, T_cam_obj: np.ndarray) -> int:
        """Pick the texture points of a frame (uint8 grey image) whose pose is `T_cam_obj`; returns how many."""
        self.reset()
        cfg, h, w = self.cfg, gray.shape[0], gray.shape[1]
        uvw = transform_points(T_cam_obj, self.vertices) @ np.asarray(K, float).T
        if uvw[:, 2].min() <= 1e-3:
            return 0
        uv = uvw[:, :2] / uvw[:, 2:3]
        x0, y0 = np.floor(np.clip(uv.min(0), 0, [w, h])).astype(int)
        x1, y1 = np.ceil(np.clip(uv.max(0) + 1, 0, [w, h])).astype(int)
        if x1 - x0 < 8 or y1 - y0 < 8:
            return 0
        K_crop = np.array(K, float)
        K_crop[0, 2] -= x0
        K_crop[1, 2] -= y0
        with torch_threads(1):  # a small render: threads would cost more than they gain
            depth = render_depth(self.vertices, self.faces, K_crop, T_cam_obj, x1 - x0, y1 - y0)
        inside = np.isfinite(depth).astype(np.uint8)
        inside = cv2.erode(inside, np.ones((2 * cfg.edge_px + 1,) * 2, np.uint8))
        corners = cv2.goodFeaturesToTrack(np.ascontiguousarray(gray[y0:y1, x0:x1]), cfg.points, cfg.quality,
                                          cfg.min_distance_px, mask=inside)
        if corners is None:
            return 0
        crop_px = corners.reshape(-1, 2)
        z = depth[np.clip(np.rint(crop_px[:, 1]).astype(int), 0, y1 - y0 - 1),
                  np.clip(np.rint(crop_px[:, 0]).astype(int), 0, x1 - x0 - 1)]
        px = crop_px + [x0, y0]
        ok = np.isfinite(z)
        rays = np.c_[px[ok], np.ones(ok.sum())] @ np.linalg.inv(K).T
        self._X = transform_points(inv_T(T_cam_obj), rays * z[ok, None])
        self._px = px[ok].reshape(-1, 1, 2).astype(np.float32)
        self._gray = gray
        return len(self._X)

    def follow(self, gray: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """(object-frame points N x 3, their pixels in `gray` N x 2) of the points selected in the last frame that
        flow follows there and back; None when fewer than `min_points` survive."""
        cfg = self.cfg
        if self._gray is None or len(self._X) < cfg.min_points or gray.shape != self._gray.shape:
            return None
        lk = {"winSize": (cfg.window_px, cfg.window_px), "maxLevel": cfg.levels,
              "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.03)}
        ahead, ok, _ = cv2.calcOpticalFlowPyrLK(self._gray, gray, self._px, None, **lk)
        back, ok_back, _ = cv2.calcOpticalFlowPyrLK(gray, self._gray, ahead, None, **lk)
        good = (ok[:, 0] == 1) & (ok_back[:, 0] == 1) & (np.linalg.norm(back - self._px, axis=2)[:, 0] <= cfg.fb_px)
        if good.sum() < cfg.min_points:
            return None
        return self._X[good], ahead[good, 0].astype(float)
