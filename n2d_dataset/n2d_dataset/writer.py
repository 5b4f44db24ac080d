"""Dataset writers: per-frame files in BOP's train_pbr layout with DOPE JSON next to each image, then the
chunk-level JSON files, the models and the camera, assembled from the per-frame records.

Layout (BOP, as bop_toolkit's docs/bop_datasets_format.md describes it):
  camera.json                        intrinsics of every frame (one fixed camera), depth_scale
  models/models_info.json, obj_NNNNNN.ply (mm), <name>/ (the n2d model, metres)
  train_pbr/CCCCCC/rgb/IIIIII.jpg    (or .png) and IIIIII.json, the DOPE annotation of that image
  train_pbr/CCCCCC/depth/IIIIII.png  uint16, depth_mm = value * depth_scale (0.1 mm steps, 0: no surface)
  train_pbr/CCCCCC/mask/IIIIII_KKKKKK.png, mask_visib/...  full and visible silhouette of instance K
  train_pbr/CCCCCC/scene_gt.json, scene_camera.json, scene_gt_info.json
  train_pbr/CCCCCC/rgb/_camera_settings.json, _object_settings.json   NDDS files the NVlabs DOPE training
                                     scripts read next to the images (intrinsics; cuboid_dimensions in cm)
A frame's files are written first and its record (records/FFFFFF.json) last, atomically: a frame without
a record is re-rendered on resume. The records become the chunk JSON files at the end, then go.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

import cv2
import numpy as np
import trimesh

from n2d_common.config import from_dict
from n2d_common.contracts import atomic_write_bytes, atomic_write_json
from n2d_common.errors import Cancelled
from n2d_common.frames import inv_T
from n2d_common.process import rss_mb
from n2d_common.progress import Progress
from n2d_dataset.annotate import Annotation, annotate, bop_camera, bop_gt, dope_frame
from n2d_dataset.config import DatasetConfig
from n2d_dataset.models import Model

DEPTH_SCALE = 0.1
"""BOP depth_scale: millimetres per unit of the uint16 depth PNGs (0.1 mm steps, up to 6.5 m)."""
RECORDS = "records"


def frame_location(frame: int, chunk_size: int) -> tuple[Path, int]:
    """(chunk directory relative to the dataset root, image id in the chunk) of frame number `frame`."""
    return Path("train_pbr") / f"{frame // chunk_size:06d}", frame % chunk_size


def _encode(path: Path, img: np.ndarray, params=()) -> None:
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(path.suffix, img, list(params))
    if not ok:
        raise OSError(f"could not encode {path}")
    atomic_write_bytes(path, buf.tobytes())


def rgb_name(im_id: int, fmt: str) -> str:
    return f"{im_id:06d}.{fmt}"


def write_frame(root: Path, frame: int, chunk_size: int, rgb: np.ndarray, fmt: str, quality: int,
                record: dict, depth_m: np.ndarray | None = None, annotations: list[Annotation] = (),
                dope: dict | None = None) -> None:
    """Write one frame's image (and, when annotated, depth, masks and DOPE JSON), then its record."""
    chunk, im = frame_location(frame, chunk_size)
    base = root / chunk
    _encode(base / "rgb" / rgb_name(im, fmt), rgb, (cv2.IMWRITE_JPEG_QUALITY, quality) if fmt == "jpg" else ())
    if depth_m is not None:
        depth = np.where(np.isfinite(depth_m), np.round(depth_m * 1000.0 / DEPTH_SCALE), 0)
        _encode(base / "depth" / f"{im:06d}.png", np.where(depth > 65535, 0, depth).astype(np.uint16))
    for k, a in enumerate(annotations):
        _encode(base / "mask" / f"{im:06d}_{k:06d}.png", a.mask.astype(np.uint8) * 255)
        _encode(base / "mask_visib" / f"{im:06d}_{k:06d}.png", a.mask_visib.astype(np.uint8) * 255)
    if dope is not None:
        atomic_write_json(base / "rgb" / f"{im:06d}.json", dope)
    atomic_write_json(root / RECORDS / f"{frame:06d}.json", record)


def write_annotated_frame(root: Path, cfg, frame: int, rgb: np.ndarray, record: dict, targets: list,
                          T_world_cam: np.ndarray, index: np.ndarray, depth_m: np.ndarray) -> None:
    """Annotate one rendered frame from its labels (instance index and planar depth at pixel centres) and write it:
    `record` (frame, in_hand, renderer, seconds of the phases so far) gains the BOP camera, ground truth and info,
    the annotation's seconds and the worker's memory; `targets` are (model, label, T_world_obj) of every target
    instance. Both renderers end their frames here."""
    t0 = time.perf_counter()
    K, r = cfg.camera.K(), cfg.render
    T_cam_world = inv_T(T_world_cam)
    record = {**record, "scene_camera": bop_camera(K, T_cam_world, DEPTH_SCALE)}
    extra = {}
    if cfg.annotate:
        annotations = [annotate(model, label, T_cam_world @ T_world_obj, K, index, depth_m)
                       for model, label, T_world_obj in targets]
        _, im = frame_location(frame, cfg.chunk_size)
        extra = {"depth_m": depth_m, "annotations": annotations,
                 "dope": dope_frame(annotations, K, cfg.camera.width, cfg.camera.height, rgb_name(im, r.rgb_format),
                                    index, depth_m)}
        record |= {"scene_gt": [bop_gt(a) for a in annotations], "scene_gt_info": [a.info for a in annotations]}
    record["rss_mb"] = round(rss_mb(), 1)
    record["seconds"] = {**record.get("seconds", {}), "annotate": time.perf_counter() - t0}
    write_frame(root, frame, cfg.chunk_size, rgb, r.rgb_format, r.jpeg_quality, record, **extra)


def render_each(frames: list[int], render_one, device: str, progress, cancel) -> dict:
    """A worker's frame loop: `render_one(frame)` for each frame, progress after each, Cancelled (with every
    finished frame kept) as soon as `cancel` is set; returns the worker's summary."""
    for n, frame in enumerate(frames):
        if cancel.is_set():
            raise Cancelled(f"stopped after {n} of this worker's {len(frames)} frames",
                            "re-run the same command to resume")
        t0 = time.perf_counter()
        render_one(frame)
        progress(Progress((n + 1) / len(frames), "rendering", message=f"frame {frame}",
                          info={"frame": frame, "seconds": time.perf_counter() - t0, "device": device}))
    return {"frames": len(frames), "device": device}


def render_shard(frame_renderer, engine: str, model_dirs: list[str], root: str, config: dict, frames: list[int],
                 progress, cancel) -> dict:
    """A local worker's job: `frame_renderer` (a worker module's) set up with the worker's share of the cores, then
    `render_each` over its frames."""
    cfg = from_dict(DatasetConfig, config)
    threads = cfg.render.threads or max(1, len(os.sched_getaffinity(0)) // cfg.worker_count(engine))
    with frame_renderer(model_dirs, config, threads) as (render_one, device):
        return render_each(frames, lambda frame: render_one(root, frame), device, progress, cancel)


def done_frames(root: Path) -> set[int]:
    """Frames whose record exists (finished, all files written)."""
    return {int(p.stem) for p in (root / RECORDS).glob("*.json")} if (root / RECORDS).is_dir() else set()


def assemble(root: Path, frames: int, chunk_size: int) -> dict:
    """Turn the per-frame records into each chunk's scene_gt/scene_camera/scene_gt_info.json; returns totals
    (instances, seconds per phase, render worker memory at the first and last frame)."""
    chunks: dict[Path, dict[str, dict]] = {}
    instances, seconds, rss = 0, {}, []
    for frame in range(frames):
        record = json.loads((root / RECORDS / f"{frame:06d}.json").read_text())
        chunk, im = frame_location(frame, chunk_size)
        files = chunks.setdefault(chunk, {"scene_gt": {}, "scene_camera": {}, "scene_gt_info": {}})
        for key in files:
            if key in record:
                files[key][str(im)] = record[key]
        instances += len(record.get("scene_gt", []))
        rss.append(record.get("rss_mb", 0.0))
        for phase, s in record.get("seconds", {}).items():
            seconds[phase] = seconds.get(phase, 0.0) + s
    for chunk, files in chunks.items():
        for key, content in files.items():
            if content:
                atomic_write_json(root / chunk / f"{key}.json", content)
    shutil.rmtree(root / RECORDS)
    return {"instances": instances, "seconds": {k: round(v, 2) for k, v in seconds.items()},
            "worker_rss_mb": {"first_frame": rss[0], "last_frame": rss[-1], "max": max(rss)}}


def write_models(root: Path, models: list[Model]) -> None:
    """models/: BOP models_info.json and obj_NNNNNN.ply (millimetres), and each n2d model as given (metres)."""
    info = {}
    for m in models:
        mesh = m.mesh
        ply = trimesh.Trimesh(mesh.vertices * 1000.0, mesh.faces, process=False).export(file_type="ply")
        atomic_write_bytes(root / "models" / f"obj_{m.obj_id:06d}.ply", ply)
        info[str(m.obj_id)] = next(iter(json.loads((m.directory / "models_info.json").read_text()).values()))
        shutil.copytree(m.directory, root / "models" / m.name, dirs_exist_ok=True,
                        ignore=shutil.ignore_patterns("*.partial", "preview.png", "report.json"))
    atomic_write_json(root / "models" / "models_info.json", info)


def write_camera(root: Path, K: np.ndarray, width: int, height: int) -> None:
    """BOP camera.json of the dataset's one camera."""
    atomic_write_json(root / "camera.json", {"cx": float(K[0, 2]), "cy": float(K[1, 2]), "fx": float(K[0, 0]),
                                             "fy": float(K[1, 1]), "width": width, "height": height,
                                             "depth_scale": DEPTH_SCALE})


def write_ndds_settings(root: Path, models: list[Model], K: np.ndarray, width: int, height: int) -> None:
    """The NDDS `_camera_settings.json` and `_object_settings.json` in every chunk's rgb/ folder, so NVlabs'
    DOPE training scripts can read the dataset as it is (cuboid dimensions in cm, as NDDS writes them)."""
    camera = {"camera_settings": [{
        "name": "n2d", "horizontal_fov": float(np.degrees(2 * np.arctan(width / (2 * K[0, 0])))),
        "intrinsic_settings": {"resX": width, "resY": height, "fx": float(K[0, 0]), "fy": float(K[1, 1]),
                               "cx": float(K[0, 2]), "cy": float(K[1, 2]), "s": 0},
        "captured_image_size": {"width": width, "height": height}}]}
    objects = {"exported_object_classes": [m.name for m in models],
               "exported_objects": [{"class": m.name, "segmentation_class_id": m.obj_id,
                                     "fixed_model_transform": np.eye(4).tolist(),
                                     "cuboid_dimensions": (100.0 * m.size_m).tolist()} for m in models]}
    for rgb in sorted((root / "train_pbr").glob("*/rgb")):
        atomic_write_json(rgb / "_camera_settings.json", camera)
        atomic_write_json(rgb / "_object_settings.json", objects)
