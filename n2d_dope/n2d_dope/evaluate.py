"""Measure a DOPE model: ADD / ADD-S accuracy and AUC, timings and overlays, on two kinds of test set.

- Held-out synthetic frames: an n2d dataset rendered with another seed; ground truth from its BOP `scene_gt.json`,
  model points from the dataset's copy of the model.
- The views of a capture session: a real turntable sweep; ground truth from the ChArUco board's camera poses and
  where the object stands on the plate.

Each true instance is matched to the detection with the smallest ADD-S; a missed instance counts as an infinite
error, and a detection within 10 % of the diameter (ADD-S) of no instance is a false detection. Results go to
`eval.json` in the DOPE model directory under NAME/PRECISION, and `eval_NAME.png` shows the detections (cuboid: red
front, green rear) over the true cuboids (white).
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import cv2
import numpy as np

from n2d_common.contracts import atomic_write_json
from n2d_common.errors import Cancelled, ContractError
from n2d_common.frames import inv_T, make_T, project
from n2d_common.images import contact_sheet, draw_axes, draw_cuboid, write_png
from n2d_common.progress import Eta, Progress, ProgressFn, no_progress
from n2d_common.symmetry import from_models_info, symmetric_poses
from n2d_dope.config import RefineConfig
from n2d_dope.data import open_dataset, read_rgb
from n2d_dope.infer import DopeModel
from n2d_dope.metrics import add, add_s, bop_recall, mspd, mspd_thresholds, mssd, mssd_thresholds, summarize

MODEL_POINTS = 2000
OVERLAYS = 12


def model_points(model_dir: Path, count: int = MODEL_POINTS) -> tuple[np.ndarray, float]:
    """`count` points on the model's surface (metres, object frame) and its diameter (metres)."""
    from n2d_common.formats.model import read_model_mesh
    from n2d_common.geometry import sample_surface

    mesh = read_model_mesh(model_dir)
    info = json.loads((model_dir / "models_info.json").read_text())
    entry = next(iter(info.values())) if "diameter" not in info else info
    return sample_surface(mesh.vertices, mesh.faces, count), float(entry["diameter"]) / 1000.0


def model_symmetries(model_dir: Path) -> list[np.ndarray]:
    """The 4 x 4 transforms the model is symmetric under (identity first; only it for an asymmetric model), from its
    models_info.json."""
    info = json.loads((model_dir / "models_info.json").read_text())
    entry = next(iter(info.values())) if "diameter" not in info else info
    return symmetric_poses(from_models_info(entry))


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


def score_images(model: DopeModel, items, total: int, points: np.ndarray, diameter: float, name: str,
           progress: ProgressFn, cancel: threading.Event | None,
           sym_poses: list[np.ndarray] | None = None, on_detections=None) -> tuple[dict, list[np.ndarray], dict]:
    """Run the model over `items` ((rgb, K, true poses) per image), match each true instance to the detection
    with the smallest ADD-S, and summarise (ADD, ADD-S; BOP's MSSD and MSPD recall under the model's symmetries
    `sym_poses`); also returns overlays of up to OVERLAYS evenly spread images and the per-instance errors
    ({"add", "adds"}: metres, inf for a miss, in the order of the instances). `on_detections(i, detections,
    seconds)` sees each image's detections."""
    sym_poses = sym_poses or [np.eye(4)]
    mssd_points = points[:: max(1, len(points) // 500)]  # MSSD / MSPD are maxima over the points: 500 suffice
    add_errors, adds_errors, network_s, post_s, refine_s, overlays = [], [], [], [], [], []
    mssd_errors, mspd_errors, width = [], [], 0
    false_detections = 0
    pick = set(np.linspace(0, total - 1, min(OVERLAYS, total)).round().astype(int).tolist())
    eta = Eta()
    for i, (rgb, K, truths) in enumerate(items):
        if cancel is not None and cancel.is_set():
            raise Cancelled("evaluation cancelled", "run it again")
        started = time.perf_counter()
        detections = model.detect(rgb, K)
        if on_detections is not None:
            on_detections(i, detections, time.perf_counter() - started)
        width = rgb.shape[1]
        network_s.append(model.timing.network)
        post_s.append(model.timing.postprocess)
        refine_s.append(model.timing.refine)
        used, frame_errors = set(), []
        for T in truths:
            scores = [(add_s(d.T_cam_obj, T, points), j) for j, d in enumerate(detections) if j not in used]
            if not scores:
                for errors in (add_errors, adds_errors, frame_errors, mssd_errors, mspd_errors):
                    errors.append(np.inf)
                continue
            err_s, j = min(scores)
            used.add(j)
            adds_errors.append(err_s)
            add_errors.append(add(detections[j].T_cam_obj, T, points))
            mssd_errors.append(mssd(detections[j].T_cam_obj, T, mssd_points, sym_poses))
            mspd_errors.append(mspd(detections[j].T_cam_obj, T, mssd_points, K, sym_poses))
            frame_errors.append(err_s)
        false_detections += sum(all(add_s(d.T_cam_obj, T, points) >= 0.1 * diameter for T in truths)
                                for d in detections)
        if i in pick:
            overlays.append(_overlay(rgb, K, truths, detections, model.cuboid_m, frame_errors))
        progress(Progress((i + 1) / total, f"evaluating {name}", eta((i + 1) / total), f"image {i + 1}/{total}"))
    result = summarize(add_errors, adds_errors, diameter)
    result["mssd_recall"] = bop_recall(mssd_errors, mssd_thresholds(diameter))
    result["mspd_recall"] = bop_recall(mspd_errors, mspd_thresholds(width or 640))
    result["symmetries"] = len(sym_poses)
    result.update({"images": total, "precision": model.precision, "false_detections": false_detections,
                   "network_ms_mean": 1000 * float(np.mean(network_s)) if network_s else None,
                   "postprocess_ms_mean": 1000 * float(np.mean(post_s)) if post_s else None,
                   "refined": model.refiner is not None,
                   "refine_ms_mean": 1000 * float(np.mean(refine_s)) if refine_s and model.refiner else None})
    return result, overlays, {"add": add_errors, "adds": adds_errors}


def record_result(model_dir: Path, name: str, result: dict, overlays: list[np.ndarray]) -> None:
    """Store `result` in eval.json under NAME/PRECISION and the overlays as eval_NAME.png."""
    if overlays:
        write_png(model_dir / f"eval_{name}.png", contact_sheet(overlays, thumb_width=min(480, overlays[0].shape[1])))
    path = model_dir / "eval.json"
    results = json.loads(path.read_text()) if path.is_file() else {}
    results[f"{name}/{result['precision']}"] = result
    atomic_write_json(path, results)


def evaluate(model_dir: str | Path, dataset_dir: str | Path, *, name: str = "synthetic", precision: str = "fp32",
             min_visibility: float = 0.25, max_frames: int = 0, refine: RefineConfig | None = None,
             progress: ProgressFn = no_progress, cancel: threading.Event | None = None) -> dict:
    """Evaluate the DOPE model on every frame of the dataset (or the first `max_frames`), its poses refined
    against the images with `refine` (against the dataset's copy of the model); returns the results and records
    them in `<model_dir>/eval.json` under `<name>/<precision>`."""
    model_dir = Path(model_dir)
    model = DopeModel(model_dir, precision=precision)
    info = open_dataset(dataset_dir)
    manifest = json.loads((info.directory / "n2d.json").read_text())
    if model.name not in manifest["extra"]["models"]:
        raise ContractError(f"{info.directory} does not show {model.name}", "evaluate on a dataset of that object")
    obj_id = manifest["extra"]["models"][model.name]
    if refine is not None:
        model.enable_refinement(refine, info.directory / "models" / model.name)
    points, diameter = model_points(info.directory / "models" / model.name)
    sym_poses = model_symmetries(info.directory / "models" / model.name)
    frames = info.frames[:max_frames] if max_frames > 0 else info.frames

    def items():
        for frame in frames:
            camera = json.loads((frame.chunk / "scene_camera.json").read_text())[str(frame.frame_id)]
            K = np.array(camera["cam_K"], dtype=float).reshape(3, 3)
            yield read_rgb(frame.image), K, _ground_truth(frame, obj_id, min_visibility)

    result, overlays, _ = score_images(model, items(), len(frames), points, diameter, name, progress, cancel, sym_poses)
    result.update({"frames": len(frames), "dataset": str(info.directory), "min_visibility": min_visibility})
    record_result(model_dir, name, result, overlays)
    return result


def session_ground_truth(session_dir: str | Path, T_turntable_obj: np.ndarray) -> list[tuple]:
    """(image path, K, distortion, T_cam_obj) of every posed view of a capture session, for an object standing
    at `T_turntable_obj` on the plate."""
    from n2d_common.formats.session import read_session

    session = read_session(session_dir)
    views = [(v.image, session.K, session.dist, inv_T(v.T_turntable_cam) @ T_turntable_obj)
             for v in session.views if v.T_turntable_cam is not None]
    if not views:
        raise ContractError(f"{session_dir} has no posed views", "capture with the board in view")
    return views


def evaluate_session(model_dir: str | Path, session_dir: str | Path, *, T_turntable_obj: np.ndarray | None = None,
                     object_model_dir: str | Path | None = None, name: str = "turntable", precision: str = "fp32",
                     refine: RefineConfig | None = None, progress: ProgressFn = no_progress,
                     cancel: threading.Event | None = None) -> dict:
    """Evaluate on the views of a capture session: a real-world test set whose ground truth is the camera pose
    from the ChArUco board composed with where the object stands on the plate.

    `T_turntable_obj` (4 x 4, model frame -> turntable frame, metres) defaults to the one the object's
    reconstructed model records in its manifest (`n2d reconstruct` writes it); `object_model_dir` (the model
    whose points ADD uses) defaults to the model the DOPE network was trained on. Capture the test sweep at
    angles not used for the reconstruction, without moving the object.
    """
    model_dir = Path(model_dir)
    model = DopeModel(model_dir, precision=precision)
    object_dir = Path(object_model_dir or model.config.get("model_dir") or "")
    if not (object_dir / "models_info.json").is_file():
        raise ContractError(f"no object model at {object_dir}", "pass the object's model directory")
    if T_turntable_obj is None:
        manifest = object_dir / "n2d.json"
        extra = json.loads(manifest.read_text()).get("extra", {}) if manifest.is_file() else {}
        stored = extra.get("T_turntable_obj")
        if stored is None:
            raise ContractError(f"{object_dir} does not record where the object stood on the plate (T_turntable_obj)",
                                "evaluate with the model n2d reconstruct made from this object's capture")
        T_turntable_obj = np.array(stored, dtype=float)
    views = session_ground_truth(session_dir, T_turntable_obj)
    if refine is not None:
        model.enable_refinement(refine, object_dir)
    points, diameter = model_points(object_dir)

    def items():
        for image, K, dist, T_cam_obj in views:
            rgb = read_rgb(image)
            yield (cv2.undistort(rgb, K, dist) if np.any(dist) else rgb), K, [T_cam_obj]

    result, overlays, _ = score_images(model, items(), len(views), points, diameter, name, progress, cancel,
                                 model_symmetries(object_dir))
    result.update({"views": len(views), "session": str(Path(session_dir).absolute()),
                   "ground_truth": "board camera poses composed with T_turntable_obj"})
    record_result(model_dir, name, result, overlays)
    return result
