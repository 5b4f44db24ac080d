"""Checks of a written dataset against its models, independent of the code that wrote it.

For every annotated instance: the visible mask (Blender's index pass) against the mesh projected with
the written pose and K, filled as polygons by OpenCV at 8x resolution (mean boundary offset = XOR area /
silhouette perimeter, on fully visible instances); the written depth against the mesh depth under the
pose (n2d's rasterizer) on visible pixels; visib_fract against a BOP-style recount (mesh depth within
5 mm of the scene depth); and the DOPE JSON against the BOP pose (location, quaternion, projected
cuboid, on the keypoints in front of the camera and near the image).
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from n2d_common.contracts import open_stage
from n2d_common.errors import ContractError
from n2d_common.frames import R_from_quat, make_T, project, transform_points
from n2d_common.images import read_png
from n2d_common.raster import render_depth
from n2d_dataset.models import load_models
from n2d_dataset.writer import DEPTH_SCALE

VISIB_DEPTH_TOLERANCE_M = 0.005
"""Recount: a silhouette pixel is visible when the scene depth is within this of the object's own depth."""


def frames(root: Path) -> Iterator[tuple[Path, int, dict, list, list, np.ndarray]]:
    """(chunk dir, image id, DOPE JSON, scene_gt list, scene_gt_info list, K) of every frame of a dataset."""
    for chunk in sorted((root / "train_pbr").iterdir()):
        gt, info, cam = (json.loads((chunk / f"{k}.json").read_text())
                         for k in ("scene_gt", "scene_gt_info", "scene_camera"))
        for im in sorted(gt, key=int):
            dope = json.loads((chunk / "rgb" / f"{int(im):06d}.json").read_text())
            yield chunk, int(im), dope, gt[im], info[im], np.array(cam[im]["cam_K"]).reshape(3, 3)


def pose(gt: dict) -> np.ndarray:
    """T_cam_obj (metres) of a BOP scene_gt entry."""
    return make_T(np.array(gt["cam_R_m2c"]).reshape(3, 3), np.array(gt["cam_t_m2c"]) / 1000.0)


def silhouette(vertices: np.ndarray, faces: np.ndarray, T_cam_obj: np.ndarray, K: np.ndarray, width: int,
               height: int, ss: int = 8) -> np.ndarray:
    """Whether each pixel centre lies inside the projected mesh, from triangles filled by OpenCV at `ss` x
    resolution (one at a time: fillPoly's even-odd rule would cancel overlapping faces)."""
    uv = project(K, T_cam_obj, vertices)
    fine = np.round((uv * ss + (ss - 1) / 2) * 16).astype(np.int32)  # pixel centre u -> centre of its block
    canvas = np.zeros((height * ss, width * ss), np.uint8)
    for tri in fine[faces]:
        cv2.fillConvexPoly(canvas, tri, 1, lineType=cv2.LINE_8, shift=4)
    return canvas[ss // 2::ss, ss // 2::ss].astype(bool)


def check_dataset(root: str | Path) -> dict:
    """Measure the annotations of the dataset in `root`; returns mean/max errors and counts.

    Raises ContractError for a dataset whose files are missing or malformed (naming the frame)."""
    root = Path(root)
    try:
        ids = dict(open_stage(root, "dataset")["extra"]["models"])  # name -> BOP obj_id
        names = sorted(ids, key=lambda n: int(ids[n]))
    except (KeyError, TypeError, ValueError) as exc:
        raise ContractError(f"the manifest of {root} has no valid extra.models ({type(exc).__name__}: {exc})",
                            _DAMAGED) from None
    models = {m.obj_id: m for m in load_models([root / "models" / name for name in names])}
    where = [root]
    try:
        return _check(root, models, where)
    except OSError as exc:
        raise ContractError(f"cannot read {exc.filename or where[-1]}: {exc.strerror or exc}", _DAMAGED) from None
    except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
        raise ContractError(f"the annotations of {root} are malformed at {where[-1]} ({type(exc).__name__}: {exc})",
                            _DAMAGED) from None


_DAMAGED = "the dataset is damaged: generate it again (n2d dataset)"


def _check(root: Path, models: dict, where: list) -> dict:
    """check_dataset's measurements; `where` gets the frame being read (for the error of a malformed one)."""
    by_name = {m.name: m for m in models.values()}
    offsets, depth_err, visib_err, dope_px, instances = [], [], [], [], 0
    for chunk, im, dope, gts, infos, K in frames(root):
        where.append(f"frame {im} of {chunk}")
        depth = cv2.imread(str(chunk / "depth" / f"{im:06d}.png"), cv2.IMREAD_UNCHANGED)
        if depth is None or depth.ndim != 2:
            raise ContractError(f"cannot read the depth image of frame {im} in {chunk}", _DAMAGED)
        depth = depth * DEPTH_SCALE / 1000.0
        h, w = depth.shape
        for k, (gt, info, obj) in enumerate(zip(gts, infos, dope["objects"])):
            instances += 1
            model = models[gt["obj_id"]]
            T = pose(gt)
            visib = read_png(chunk / "mask_visib" / f"{im:06d}_{k:06d}.png") > 0
            own = render_depth(model.mesh.vertices, model.mesh.faces, K, T, w, h)
            seen = visib & np.isfinite(own) & (depth > 0)
            depth_err.append(np.abs(depth[seen] - own[seen]))
            if info["visib_fract"] > 0.999 and info["px_count_visib"] >= 100:
                truth = silhouette(model.mesh.vertices, model.mesh.faces, T, K, w, h)
                contours, _ = cv2.findContours(truth.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
                offsets.append((visib ^ truth).sum() / sum(cv2.arcLength(c, True) for c in contours))
            x, y, bw, bh = info["bbox_obj"]
            if x >= 0 and y >= 0 and x + bw <= w and y + bh <= h and info["px_count_all"] >= 100:
                full = np.isfinite(own)
                recount = (full & (depth > 0) & (np.abs(depth - own) < VISIB_DEPTH_TOLERANCE_M)).sum() / full.sum()
                visib_err.append(abs(recount - info["visib_fract"]))
            cuboid = by_name[obj["class"]].cuboid()
            R = R_from_quat(obj["quaternion_xyzw"])
            T_dope = make_T(R, np.array(obj["location"]) / 100.0)
            # keypoints behind the camera or far outside the image project to huge, meaningless numbers
            written = np.array(obj["projected_cuboid"])
            near = (transform_points(T_dope, cuboid)[:, 2] > 0.01) & (np.abs(written) < 4 * max(w, h)).all(1)
            dope_px.append(np.abs(written - project(K, T_dope, cuboid))[near].max(initial=0.0))
    depth_err = np.concatenate(depth_err) if depth_err else np.zeros(0)
    return {"instances": instances, "fully_visible_instances": len(offsets),
            "mask_boundary_offset_px": {"mean": float(np.mean(offsets)) if offsets else None,
                                        "max": float(np.max(offsets)) if offsets else None},
            "depth_error_mm": {"mean": 1000 * float(depth_err.mean()) if depth_err.size else None,
                               "p95": 1000 * float(np.percentile(depth_err, 95)) if depth_err.size else None},
            "visib_fract_error": {"mean": float(np.mean(visib_err)) if visib_err else None,
                                  "max": float(np.max(visib_err)) if visib_err else None},
            "dope_vs_pose_px_max": float(np.max(dope_px)) if dope_px else None}
