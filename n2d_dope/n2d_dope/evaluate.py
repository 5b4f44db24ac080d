"""Measure a DOPE model on held-out frames of an n2d dataset: ADD / ADD-S accuracy and AUC, timings, overlays.

Ground truth comes from the dataset's BOP `scene_gt.json` (pose in mm) and model points from the dataset's copy
of the object's model. Each true instance (at least `min_visibility` visible) is matched to the detection with
the smallest ADD-S; a missed instance counts as an infinite error. Results go to `eval.json` in the DOPE model
directory under the test set's name, and `eval_<name>.png` shows the detections (cuboid: red front, green rear)
over the true cuboids (white).
"""

from __future__ import annotations

import json
import threading
from pathlib import Path

import cv2
import numpy as np

from n2d_common.contracts import atomic_write_json
from n2d_common.errors import Cancelled
from n2d_common.frames import make_T, project
from n2d_common.images import contact_sheet, draw_axes, draw_cuboid, write_png
from n2d_common.progress import Eta, Progress, ProgressFn, no_progress
from n2d_dope.data import open_dataset, read_rgb
from n2d_dope.infer import DopeModel
from n2d_dope.metrics import add, add_s, summarize

MODEL_POINTS = 2000
OVERLAYS = 12


def model_points(model_dir: Path, count: int = MODEL_POINTS) -> tuple[np.ndarray, float]:
    """`count` points on the model's surface (metres, object frame) and its diameter (metres)."""
    from n2d_reconstruct.export import read_model_mesh
    from n2d_reconstruct.metrics import sample_surface

    mesh = read_model_mesh(model_dir)
    info = json.loads((model_dir / "models_info.json").read_text())
    entry = next(iter(info.values())) if "diameter" not in info else info
    return sample_surface(mesh.vertices, mesh.faces, count), float(entry["diameter"]) / 1000.0


def _ground_truth(frame, obj_id: int, min_visibility: float) -> list[np.ndarray]:
    scene_gt = json.loads((frame.chunk / "scene_gt.json").read_text())[str(frame.frame_id)]
    info = json.loads((frame.chunk / "scene_gt_info.json").read_text())[str(frame.frame_id)]
    return [make_T(np.array(g["cam_R_m2c"]).reshape(3, 3), np.array(g["cam_t_m2c"]) / 1000.0)
            for g, i in zip(scene_gt, info) if g["obj_id"] == obj_id and i["visib_fract"] >= min_visibility]


def _overlay(rgb: np.ndarray, K: np.ndarray, truths: list[np.ndarray], detections, cuboid: np.ndarray,
             errors: list[float]) -> np.ndarray:
    out = rgb.copy()
    for T in truths:
        draw_cuboid(out, project(K, T, cuboid)[:8], (255, 255, 255), (255, 255, 255))
    for d in detections:
        draw_cuboid(out, project(K, d.T_cam_obj, cuboid)[:8], thickness=2)
        draw_axes(out, K, d.T_cam_obj, 0.5 * float(np.ptp(cuboid[:8, 0])))
    text = " ".join("miss" if not np.isfinite(e) else f"{1000 * e:.1f}mm" for e in errors)
    cv2.putText(out, f"ADD-S {text}", (4, out.shape[0] - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 0), 1,
                cv2.LINE_AA)
    return out


def evaluate(model_dir: str | Path, dataset_dir: str | Path, *, name: str = "synthetic", precision: str = "fp32",
             min_visibility: float = 0.25, max_frames: int = 0, progress: ProgressFn = no_progress,
             cancel: threading.Event | None = None) -> dict:
    """Evaluate the DOPE model on every frame of the dataset (or the first `max_frames`); returns the results
    and records them in `<model_dir>/eval.json` under `<name>/<precision>`."""
    model_dir = Path(model_dir)
    model = DopeModel(model_dir, precision=precision)
    info = open_dataset(dataset_dir)
    manifest = json.loads((info.directory / "n2d.json").read_text())
    obj_id = manifest["extra"]["models"][model.name]
    points, diameter = model_points(info.directory / "models" / model.name)
    frames = info.frames[:max_frames] if max_frames > 0 else info.frames
    add_errors, adds_errors, network_s, post_s, overlays = [], [], [], [], []
    pick = set(np.linspace(0, len(frames) - 1, min(OVERLAYS, len(frames))).round().astype(int).tolist())
    eta = Eta()
    for i, frame in enumerate(frames):
        if cancel is not None and cancel.is_set():
            raise Cancelled("evaluation cancelled", "run it again")
        camera = json.loads((frame.chunk / "scene_camera.json").read_text())[str(frame.frame_id)]
        K = np.array(camera["cam_K"], dtype=float).reshape(3, 3)
        rgb = read_rgb(frame.image)
        truths = _ground_truth(frame, obj_id, min_visibility)
        detections = model.detect(rgb, K)
        network_s.append(model.timing.network)
        post_s.append(model.timing.postprocess)
        used, frame_errors = set(), []
        for T in truths:
            scores = [(add_s(d.T_cam_obj, T, points), j) for j, d in enumerate(detections) if j not in used]
            if not scores:
                add_errors.append(np.inf)
                adds_errors.append(np.inf)
                frame_errors.append(np.inf)
                continue
            err_s, j = min(scores)
            used.add(j)
            adds_errors.append(err_s)
            add_errors.append(add(detections[j].T_cam_obj, T, points))
            frame_errors.append(err_s)
        if i in pick:
            overlays.append(_overlay(rgb, K, truths, detections, model.cuboid_m, frame_errors))
        progress(Progress((i + 1) / len(frames), "evaluating", eta((i + 1) / len(frames)),
                          f"frame {i + 1}/{len(frames)}"))
    result = summarize(add_errors, adds_errors, diameter)
    result.update({"frames": len(frames), "precision": precision, "dataset": str(info.directory),
                   "min_visibility": min_visibility, "network_ms_mean": 1000 * float(np.mean(network_s)),
                   "postprocess_ms_mean": 1000 * float(np.mean(post_s))})
    if overlays:
        write_png(model_dir / f"eval_{name}.png", contact_sheet(overlays, thumb_width=min(480, overlays[0].shape[1])))
    path = model_dir / "eval.json"
    results = json.loads(path.read_text()) if path.is_file() else {}
    results[f"{name}/{precision}"] = result
    atomic_write_json(path, results)
    return result
