"""Annotations of one frame from its label render: masks, BOP ground truth and info, DOPE objects.

Pure numpy (plus n2d's CPU rasterizer). Inputs: each target's pose `T_cam_obj` (OpenCV camera frame,
metres), the intrinsics K, and the label render (Object Index and planar depth at pixel centres).
The full (unoccluded) silhouette of each target is rasterized from its mesh and pose over a canvas
twice the image size, so an object cut by the image border keeps its whole silhouette, as BOP wants
for `px_count_all` and `bbox_obj`; the visible mask is the index pass. Units: metres here, converted
by the writers (BOP mm, DOPE cm).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from n2d_common.frames import project, quat_from_R, transform_points
from n2d_common.raster import render_depth
from n2d_dataset.models import Model

KEYPOINT_DEPTH_TOLERANCE_M = 0.01
"""A cuboid keypoint counts as occluded when another surface lies this much nearer than it."""


@dataclass
class Annotation:
    """One target instance in one frame."""

    model: Model
    index: int
    """Object Index of the instance in the label render."""
    T_cam_obj: np.ndarray
    """4x4 pose of the object in the OpenCV camera frame, metres."""
    mask: np.ndarray
    """H x W bool: the full silhouette inside the image (as if nothing occluded it)."""
    mask_visib: np.ndarray
    """H x W bool: the visible part (index pass)."""
    info: dict
    """BOP scene_gt_info entry."""


def _bbox(mask: np.ndarray, dx: int = 0, dy: int = 0) -> list[int]:
    ys, xs = np.nonzero(mask)
    if not len(xs):
        return [-1, -1, 0, 0]
    return [int(xs.min()) - dx, int(ys.min()) - dy, int(xs.max() - xs.min() + 1), int(ys.max() - ys.min() + 1)]


def annotate(model: Model, index: int, T_cam_obj: np.ndarray, K: np.ndarray, label_index: np.ndarray,
             label_depth: np.ndarray) -> Annotation:
    """Masks and BOP info of one instance from its pose and the label render."""
    h, w = label_index.shape
    px, py = w // 2, h // 2
    K_big = K.copy()
    K_big[0, 2] += px
    K_big[1, 2] += py
    mesh = model.mesh
    full = np.isfinite(render_depth(mesh.vertices, mesh.faces, K_big, T_cam_obj, w + 2 * px, h + 2 * py))
    mask = full[py:py + h, px:px + w]
    visib = label_index == index
    n_all, n_visib = int(full.sum()), int((visib & mask).sum())
    info = {"bbox_obj": _bbox(full, px, py), "bbox_visib": _bbox(visib),
            "px_count_all": n_all, "px_count_valid": int((mask & np.isfinite(label_depth)).sum()),
            "px_count_visib": n_visib, "visib_fract": round(n_visib / n_all, 6) if n_all else 0.0}
    return Annotation(model, index, T_cam_obj, mask, visib, info)


def bop_gt(a: Annotation) -> dict:
    """BOP scene_gt entry: model-to-camera rotation (row-major) and translation in millimetres."""
    return {"cam_R_m2c": [float(v) for v in a.T_cam_obj[:3, :3].ravel()],
            "cam_t_m2c": [float(v) for v in 1000.0 * a.T_cam_obj[:3, 3]], "obj_id": a.model.obj_id}


def bop_camera(K: np.ndarray, T_cam_world: np.ndarray, depth_scale: float) -> dict:
    """BOP scene_camera entry (world-to-camera translation in millimetres)."""
    return {"cam_K": [float(v) for v in K.ravel()], "depth_scale": depth_scale,
            "cam_R_w2c": [float(v) for v in T_cam_world[:3, :3].ravel()],
            "cam_t_w2c": [float(v) for v in 1000.0 * T_cam_world[:3, 3]]}


def dope_object(a: Annotation, K: np.ndarray, label_index: np.ndarray, label_depth: np.ndarray) -> dict:
    """DOPE/NDDS object entry: pose in the camera frame (cm), the 8 cuboid corners and the centroid projected
    (pixels, DOPE order), and per keypoint whether it is in the image and not hidden by another surface."""
    h, w = label_index.shape
    cuboid = a.model.cuboid()
    cam = transform_points(a.T_cam_obj, cuboid)
    uv = project(K, a.T_cam_obj, cuboid)
    visible = []
    for (u, v), z in zip(uv, cam[:, 2]):
        x, y = int(round(u)), int(round(v))
        inside = z > 0 and 0 <= x < w and 0 <= y < h
        ok = inside and (label_index[y, x] == a.index or label_depth[y, x] >= z - KEYPOINT_DEPTH_TOLERANCE_M)
        visible.append(int(ok))
    return {"class": a.model.name, "name": f"{a.model.name}_{a.index:03d}", "obj_id": a.model.obj_id,
            "location": [float(v) for v in 100.0 * a.T_cam_obj[:3, 3]],
            "quaternion_xyzw": [float(v) for v in quat_from_R(a.T_cam_obj[:3, :3])],
            "cuboid_centroid": [float(v) for v in 100.0 * cam[8]],
            "projected_cuboid_centroid": [float(v) for v in uv[8]],
            "cuboid": [[float(c) for c in p] for p in 100.0 * cam[:8]],
            "projected_cuboid": [[float(c) for c in p] for p in uv],
            "keypoint_visibility": visible,
            "bounding_box": {"top_left_xy": a.info["bbox_visib"][:2],
                             "bottom_right_xy": [a.info["bbox_visib"][0] + a.info["bbox_visib"][2],
                                                 a.info["bbox_visib"][1] + a.info["bbox_visib"][3]]},
            "visibility": a.info["visib_fract"],
            "px_count_visib": a.info["px_count_visib"]}


def dope_frame(annotations: list[Annotation], K: np.ndarray, width: int, height: int, image: str,
               label_index: np.ndarray, label_depth: np.ndarray) -> dict:
    """The DOPE JSON of a frame: camera data and one entry per target instance."""
    return {"camera_data": {"width": width, "height": height,
                            "intrinsics": {"fx": float(K[0, 0]), "fy": float(K[1, 1]),
                                           "cx": float(K[0, 2]), "cy": float(K[1, 2])}},
            "image": image,
            "objects": [dope_object(a, K, label_index, label_depth) for a in annotations]}
