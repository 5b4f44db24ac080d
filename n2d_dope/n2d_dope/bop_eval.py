"""Score a DOPE model on any BOP-format test split, and write BOP's results CSV.

A BOP dataset directory holds `models/` (`obj_NNNNNN.ply` in millimetres and `models_info.json`) and one folder
per split (`test/`, `val/`, `train_pbr/`, ...) of scenes `SSSSSS/` with `scene_gt.json`, `scene_camera.json`,
`scene_gt_info.json` and `rgb/` (or `gray/`) images named by image id; an n2d dataset is one (split `train_pbr`).
`read_split` yields each image with its camera and the true poses of one object (the BOP19 targets file, when
given, picks the images); `evaluate_bop` runs the model over them and scores ADD, ADD-S, BOP's MSSD and MSPD
recall (under the object's symmetries from models_info.json) and ADD-S accuracy per visibility bucket; `write_csv`
writes the detections as BOP's toolkit reads them (`scene_id,im_id,obj_id,score,R,t,time`: R row-major, t in
millimetres, time in seconds per image).
"""

from __future__ import annotations

import csv
import json
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from n2d_common.contracts import atomic_write_text
from n2d_common.errors import ContractError
from n2d_common.frames import make_T
from n2d_common.progress import ProgressFn, no_progress
from n2d_common.symmetry import from_models_info, symmetric_poses
from n2d_dope.config import RefineConfig
from n2d_dope.data import read_rgb
from n2d_dope.evaluate import record_result, score_images
from n2d_dope.infer import DopeModel

VISIBILITY_BUCKETS = ((0.1, 0.3), (0.3, 0.6), (0.6, 1.01))
"""Visible-fraction ranges the ADD-S accuracy is also reported for."""
CSV_COLUMNS = ("scene_id", "im_id", "obj_id", "score", "R", "t", "time")


@dataclass
class BopImage:
    """One test image of a BOP split and the truth of one object in it."""

    scene_id: int
    im_id: int
    path: Path
    K: np.ndarray
    """3 x 3 intrinsics."""
    truths: list[np.ndarray]
    """4 x 4 T_cam_obj of each instance of the object (metres)."""
    visible: list[float]
    """Visible fraction of each (BOP's visib_fract; 1 when scene_gt_info.json is missing)."""


def _json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise ContractError(f"{path} is missing", "give a BOP dataset directory and a split it has") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ContractError(f"{path} is not valid JSON ({exc})", "check the dataset's files") from None


def model_info(bop_dir: Path, object_id: int) -> dict:
    """The models_info.json entry of an object (millimetres)."""
    path = bop_dir / "models" / "models_info.json"
    info = _json(path)
    if str(object_id) not in info:
        raise ContractError(f"{path} has no object {object_id}", f"objects there: {', '.join(sorted(info, key=int))}")
    entry = info[str(object_id)]
    try:
        diameter = float(entry["diameter"])
    except (KeyError, TypeError, ValueError):
        raise ContractError(f"{path}: object {object_id} has no numeric diameter", "BOP writes it in mm") from None
    if not np.isfinite(diameter) or diameter <= 0:
        raise ContractError(f"{path}: object {object_id} has diameter {diameter}", "BOP writes it in mm, > 0")
    return entry


def model_points(bop_dir: Path, object_id: int) -> np.ndarray:
    """The vertices of `models/obj_NNNNNN.ply`, in metres."""
    import trimesh

    path = bop_dir / "models" / f"obj_{object_id:06d}.ply"
    if not path.is_file():
        raise ContractError(f"{path} is missing", "give the BOP dataset's models folder")
    mesh = trimesh.load(path, force="mesh", process=False)
    return np.asarray(mesh.vertices, float) / 1000.0


def _image_path(scene: Path, im_id: int) -> Path:
    for folder in ("rgb", "gray"):
        for ext in (".png", ".jpg", ".tif"):
            path = scene / folder / f"{im_id:06d}{ext}"
            if path.is_file():
                return path
    raise ContractError(f"{scene} has no image {im_id:06d} in rgb/ or gray/", "check the split's images")


def read_split(bop_dir: str | Path, object_id: int, split: str = "test", targets: str | Path | None = None
               ) -> Iterator[BopImage]:
    """The images of a BOP split that show the object (or those the BOP19 targets file names for it)."""
    root = Path(bop_dir) / split
    if not root.is_dir():
        raise ContractError(f"{bop_dir} has no split {split!r}",
                            "splits there: " + ", ".join(p.name for p in Path(bop_dir).iterdir() if p.is_dir()))
    wanted = None
    if targets is not None:
        wanted = {(int(t["scene_id"]), int(t["im_id"])) for t in json.loads(Path(targets).read_text())
                  if int(t["obj_id"]) == object_id}
    for scene in sorted(p for p in root.iterdir() if p.is_dir() and p.name.isdigit()):
        gt, cameras = _json(scene / "scene_gt.json"), _json(scene / "scene_camera.json")
        info_path = scene / "scene_gt_info.json"
        info = _json(info_path) if info_path.is_file() else {}
        for key in sorted(gt, key=int):
            if wanted is not None and (int(scene.name), int(key)) not in wanted:
                continue
            try:
                image = _parse_image(scene, key, gt[key], cameras, info.get(key), object_id, wanted is not None)
            except (KeyError, TypeError, ValueError) as exc:
                raise ContractError(f"{scene}: image {key} has a malformed or missing entry ({exc!r})",
                                    "scene_gt.json needs obj_id, cam_R_m2c (9), cam_t_m2c (mm); "
                                    "scene_camera.json cam_K (9)") from None
            if image is not None:
                yield image


def _parse_image(scene: Path, key: str, gt: list, cameras: dict, info: list | None, object_id: int,
                 targeted: bool) -> BopImage | None:
    """One image's entries of a scene's JSON files, for one object (None: the object is not in it and no
    targets file asks for the image)."""
    rows = [(g, i) for g, i in zip(gt, info or [{}] * len(gt)) if int(g["obj_id"]) == object_id]
    if not rows and not targeted:
        return None
    truths = [make_T(np.array(g["cam_R_m2c"], float).reshape(3, 3), np.array(g["cam_t_m2c"], float).reshape(3) / 1000)
              for g, _ in rows]
    K = np.array(cameras[key]["cam_K"], float).reshape(3, 3)
    if not (np.isfinite(K).all() and all(np.isfinite(T).all() for T in truths)):
        raise ValueError("non-finite pose or intrinsics")
    return BopImage(int(scene.name), int(key), _image_path(scene, int(key)), K, truths,
                    [float(i.get("visib_fract", 1.0)) for _, i in rows])


def write_csv(path: str | Path, rows: list[tuple]) -> None:
    """BOP's results CSV (atomically): one row per detection (scene_id, im_id, obj_id, score, R 3 x 3, t metres,
    seconds for the image); R is written row-major and t in millimetres, space-separated, as BOP reads them."""
    lines = [",".join(CSV_COLUMNS)]
    for scene_id, im_id, obj_id, score, R, t, seconds in rows:
        lines.append(f"{scene_id},{im_id},{obj_id},{score:.6f},{' '.join(f'{v:.8f}' for v in np.ravel(R))},"
                     f"{' '.join(f'{1000 * v:.4f}' for v in np.ravel(t))},{seconds:.4f}")
    atomic_write_text(path, "\n".join(lines) + "\n")


def read_csv(path: str | Path) -> list[dict]:
    """The rows of a BOP results CSV, with R (3 x 3) and t (metres) as arrays."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    for r in rows:
        r["R"] = np.array(r["R"].split(), float).reshape(3, 3)
        r["t"] = np.array(r["t"].split(), float) / 1000.0
    return rows


def evaluate_bop(model_dir: str | Path, bop_dir: str | Path, object_id: int, *, split: str = "test",
                 targets: str | Path | None = None, name: str | None = None, precision: str = "fp32",
                 refine: RefineConfig | None = None, min_visibility: float = 0.1, max_images: int = 0,
                 csv_path: str | Path | None = None, progress: ProgressFn = no_progress,
                 cancel: threading.Event | None = None) -> dict:
    """Score the DOPE model on object `object_id` of a BOP split; results go to eval.json under NAME/PRECISION
    (NAME default `bop_<split>`), the detections to `csv_path` (default `<model_dir>/bop_<split>.csv`)."""
    model_dir = Path(model_dir)
    model = DopeModel(model_dir, precision=precision, refine=refine)
    name = name or f"bop_{split}"
    result, overlays = score_bop(model, bop_dir, object_id, split=split, targets=targets,
                                 min_visibility=min_visibility, max_images=max_images,
                                 csv_path=Path(csv_path) if csv_path else model_dir / f"bop_{split}.csv",
                                 name=name, progress=progress, cancel=cancel)
    record_result(model_dir, name, result, overlays)
    return result


def score_bop(model, bop_dir: str | Path, object_id: int, *, split: str = "test", targets: str | Path | None = None,
              min_visibility: float = 0.1, max_images: int = 0, csv_path: str | Path | None = None,
              name: str = "bop", progress: ProgressFn = no_progress, cancel: threading.Event | None = None
              ) -> tuple[dict, list[np.ndarray]]:
    """`evaluate_bop` for any detector with DopeModel's `detect`, `timing`, `precision`, `refiner` and `cuboid_m`:
    (the results, overlays); writes the CSV when `csv_path` is given."""
    bop_dir = Path(bop_dir)
    info = model_info(bop_dir, object_id)
    points = model_points(bop_dir, object_id)
    points = points[np.random.default_rng(0).choice(len(points), min(len(points), 2000), replace=False)]
    diameter = float(info["diameter"]) / 1000.0
    images = list(read_split(bop_dir, object_id, split, targets))
    if max_images > 0:
        images = images[:max_images]
    if not images:
        raise ContractError(f"no image of {split!r} in {bop_dir} shows object {object_id}",
                            "check --object-id and --split")
    csv_rows: list[tuple] = []
    visibility: list[float] = []

    def items():
        for im in images:
            keep = [v >= min_visibility for v in im.visible]
            visibility.extend(v for v, k in zip(im.visible, keep) if k)
            yield read_rgb(im.path), im.K, [T for T, k in zip(im.truths, keep) if k]

    def on_detections(i: int, detections, seconds: float) -> None:
        im = images[i]
        csv_rows.extend((im.scene_id, im.im_id, object_id, d.score, d.T_cam_obj[:3, :3], d.T_cam_obj[:3, 3], seconds)
                        for d in detections)

    t0 = time.perf_counter()
    result, overlays, per_instance = score_images(model, items(), len(images), points, diameter, name, progress,
                                                  cancel, symmetric_poses(from_models_info(info)), on_detections)
    adds, vis = np.array(per_instance["adds"]), np.array(visibility)
    buckets = {}
    for lo, hi in VISIBILITY_BUCKETS:
        inside = (vis >= lo) & (vis < hi)
        buckets[f"{lo:.1f}-{min(hi, 1.0):.1f}"] = {
            "instances": int(inside.sum()),
            "adds_accuracy_10pct": float(np.mean(adds[inside] < 0.1 * diameter)) if inside.any() else None}
    if csv_path is not None:
        write_csv(csv_path, csv_rows)
    result.update({"visibility_buckets": buckets, "bop_dir": str(bop_dir.absolute()), "split": split,
                   "object_id": object_id, "targets": str(targets) if targets else None,
                   "csv": str(csv_path) if csv_path else None, "seconds": round(time.perf_counter() - t0, 1)})
    return result, overlays
