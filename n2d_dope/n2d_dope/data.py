"""Training data of DOPE: the frames of an n2d dataset showing one object, augmented, with their targets.

A dataset (from `n2d dataset`) holds BOP `train_pbr/<chunk>/rgb/<frame>.jpg` with a DOPE JSON beside each image
and the visible masks in `mask_visib/`. The cuboid of each object, and the corner order, are in its manifest.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch

from n2d_common.contracts import open_stage
from n2d_common.errors import ConfigError, ContractError
from n2d_common.frames import R_from_quat, make_T, project
from n2d_common.images import looks_complete
from n2d_common.symmetry import canonical_pose, from_models_info, symmetric_poses
from n2d_dope.config import AugmentConfig, TrainConfig
from n2d_dope.network import STRIDE
from n2d_dope.targets import make_targets


@dataclass(frozen=True)
class Frame:
    """One dataset image and its annotations."""

    image: Path
    annotation: Path
    chunk: Path
    frame_id: int
    photoreal: bool = True
    """Rendered with Cycles (False: the fast rasterizer)."""

    def masks(self) -> list[Path]:
        """Visible masks of every annotated instance in the frame (all objects)."""
        return sorted((self.chunk / "mask_visib").glob(f"{self.frame_id:06d}_*.png"))


@dataclass(frozen=True)
class DatasetInfo:
    """What training and evaluation need from a dataset's manifest."""

    directory: Path
    frames: list[Frame]
    cuboid_points_m: dict[str, np.ndarray]
    """Object name -> 9 x 3 keypoints (8 corners + centroid, the manifest's order) in the object frame, metres."""
    cuboid_order: list[str]
    focal_px: float
    image_size: tuple[int, int]
    models: dict[str, str]
    """Object name -> model directory."""
    sources: dict[Path, list[str]] = field(default_factory=dict)
    """Each dataset read -> the objects it shows."""
    symmetries: dict[str, list[np.ndarray]] = field(default_factory=dict)
    """Object name -> the 4 x 4 model-frame transforms it is symmetric under (identity first; from the dataset's
    models_info.json), for the objects that have symmetries."""


def open_dataset(directory: str | Path) -> DatasetInfo:
    """Read a complete n2d dataset: its frames (sorted) and the cuboids of its objects."""
    directory = Path(directory)
    manifest = open_stage(directory, "dataset")
    try:
        extra, camera = manifest["extra"], manifest["config"]["camera"]
        if not extra.get("annotated", True):
            raise ContractError(f"{directory} was rendered without annotations", "generate it with annotate: true")
        signs = np.array(extra["cuboid_signs"], dtype=float)
        if signs.shape != (9, 3):
            raise ValueError(f"cuboid_signs is {signs.shape}, not 9 x 3")
        cuboids = {str(name): np.array(c["center"], float) + signs * np.array(c["size"], float) / 2
                   for name, c in extra["cuboids_m"].items()}
        chunk_size = int(manifest["config"].get("chunk_size", 1000))
        # Datasets written before the fast path existed are all Cycles frames.
        photoreal = int(extra.get("photoreal_frames", extra.get("frames", 0)
                                  if extra.get("renderer", "cycles") == "cycles" else 0))
        focal, size = float(camera["focal_px"]), (int(camera["width"]), int(camera["height"]))
        if not (np.isfinite(focal) and focal > 0 and min(size) > 0 and chunk_size > 0):
            raise ValueError(f"camera focal_px {focal}, size {size}, chunk_size {chunk_size}")
        if not all(np.isfinite(c).all() for c in cuboids.values()):
            raise ValueError("a cuboid is not finite")
        cuboid_order, inputs = [str(k) for k in extra["cuboid_order"]], dict(manifest["inputs"])
        obj_ids = dict(extra.get("models", {}))
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        what = f"has no {exc}" if isinstance(exc, KeyError) else f"is malformed ({type(exc).__name__}: {exc})"
        raise ContractError(f"the manifest of {directory} {what}", _DAMAGED) from None
    frames = []
    for annotation in sorted(directory.glob("train_pbr/*/rgb/*.json")):
        image = next((annotation.with_suffix(s) for s in (".jpg", ".png") if annotation.with_suffix(s).is_file()),
                     None)
        if image is not None:
            if not looks_complete(image):
                raise ContractError(f"{image} is truncated or not an image", _DAMAGED)
            check_annotation(annotation)
            chunk = annotation.parent.parent
            index = int(chunk.name) * chunk_size + int(annotation.stem)
            frames.append(Frame(image, annotation, chunk, int(annotation.stem), index < photoreal))
    if not frames:
        raise ContractError(f"{directory} has no frames with DOPE annotations (train_pbr/*/rgb/*.json)",
                            "generate the dataset with n2d dataset")
    return DatasetInfo(directory, frames, cuboids, cuboid_order, focal, size, inputs, {directory: sorted(cuboids)},
                       _symmetries(directory, obj_ids))


_DAMAGED = "the dataset is damaged: generate it again (n2d dataset)"


def check_annotation(path: Path) -> dict:
    """A frame's DOPE annotation, checked to hold what training reads (ContractError otherwise)."""
    try:
        annotation = json.loads(path.read_text())
        intrinsics = annotation.get("camera_data", {}).get("intrinsics")
        if intrinsics is not None:
            [float(intrinsics[k]) for k in ("fx", "fy", "cx", "cy")]
        for obj in annotation["objects"]:
            if not isinstance(obj["class"], str) or np.asarray(obj["projected_cuboid"], float).shape != (9, 2):
                raise ValueError("an object needs a class name and 9 projected keypoints")
            float(obj.get("visibility", 1.0))
            if np.asarray(obj.get("keypoint_visibility", [1] * 9), float).shape != (9,):
                raise ValueError("keypoint_visibility must have 9 entries")
            if intrinsics is not None:
                np.asarray(obj["location"], float).reshape(3)
                np.asarray(obj["quaternion_xyzw"], float).reshape(4)
    except OSError as exc:
        raise ContractError(f"cannot read {path}: {exc.strerror or exc}", _DAMAGED) from None
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        what = f"has no {exc}" if isinstance(exc, KeyError) else f"is malformed ({type(exc).__name__}: {exc})"
        raise ContractError(f"{path} {what}", _DAMAGED) from None
    return annotation


def _symmetries(directory: Path, obj_ids: dict[str, int]) -> dict[str, list[np.ndarray]]:
    """The symmetric poses of each object of a dataset that has symmetries (models/models_info.json)."""
    path = directory / "models" / "models_info.json"
    if not path.is_file():
        return {}
    entries = json.loads(path.read_text())
    out = {}
    for name, obj_id in obj_ids.items():
        if str(obj_id) in entries:
            poses = symmetric_poses(from_models_info(entries[str(obj_id)]))
            if len(poses) > 1:
                out[name] = poses
    return out


def open_datasets(directories: list[str | Path]) -> DatasetInfo:
    """Several complete n2d datasets as one: their frames in the order given, their objects together.

    They must share the camera (the model learns objects at the sizes in pixels they had) and the cuboid of every
    object they have in common; `directory` is the first one's."""
    infos = [open_dataset(d) for d in directories]
    if not infos:
        raise ConfigError("no dataset given", "name at least one dataset directory (from n2d dataset)")
    first = infos[0]
    cuboids, models = dict(first.cuboid_points_m), dict(first.models)
    for info in infos[1:]:
        camera, first_camera = (info.focal_px, info.image_size), (first.focal_px, first.image_size)
        if camera != first_camera or info.cuboid_order != first.cuboid_order:
            raise ConfigError(f"{info.directory} has camera (focal px, size) {camera} and corner order "
                              f"{info.cuboid_order}, {first.directory} {first_camera} and {first.cuboid_order}",
                              "train on datasets rendered with the same camera config")
        for name, cuboid in info.cuboid_points_m.items():
            if name in cuboids and not np.allclose(cuboids[name], cuboid, atol=1e-6):
                raise ConfigError(f"{name} has another cuboid in {info.directory} than in {first.directory}",
                                  "train on datasets rendered from the same model of the object")
            cuboids[name] = cuboid
        models.update({k: v for k, v in info.models.items() if k not in models})
    symmetries: dict[str, list[np.ndarray]] = {}
    for info in infos:
        for name, poses in info.symmetries.items():
            symmetries.setdefault(name, poses)
    return DatasetInfo(first.directory, [f for info in infos for f in info.frames], cuboids, first.cuboid_order,
                       first.focal_px, first.image_size, models, {d: o for i in infos for d, o in i.sources.items()},
                       symmetries)


def epoch_order(frames: list[Frame], photoreal_mix: float, rng: np.random.Generator) -> np.ndarray:
    """The frame indices of one training epoch (as many as there are frames).

    photoreal_mix < 0: every frame once, shuffled. Otherwise each sample is a photoreal (Cycles) frame with that
    probability and a fast-path frame else, each kind gone through in a shuffled order of its own (again when
    used up), so the mix holds however many frames of each kind the dataset has."""
    if photoreal_mix < 0:
        return rng.permutation(len(frames))
    kinds = np.array([f.photoreal for f in frames])
    pools = [np.flatnonzero(~kinds), np.flatnonzero(kinds)]
    draws = (rng.random(len(frames)) < photoreal_mix).astype(int)
    order = np.empty(len(frames), np.int64)
    for kind, pool in enumerate(pools):
        slots = np.flatnonzero(draws == kind)
        if len(slots):
            repeats = -(-len(slots) // len(pool))
            order[slots] = np.concatenate([rng.permutation(pool) for _ in range(repeats)])[:len(slots)]
    return order


def check_mix(info: DatasetInfo, frames: list[Frame], object_name: str, photoreal_mix: float) -> None:
    """ConfigError unless every dataset shows the object and the frames have both kinds a mix asks for."""
    for directory, objects in info.sources.items():
        if object_name != ANY_OBJECT and object_name not in objects:
            raise ConfigError(f"{directory} shows {', '.join(objects)}, not {object_name}",
                              "train on datasets rendered from the model of the same object")
    if not -1 <= photoreal_mix <= 1 or (photoreal_mix < 0 and photoreal_mix != -1):
        raise ConfigError(f"photoreal_mix is a probability in 0..1, or -1 for the frames as they come; got "
                          f"{photoreal_mix}", "set photoreal_mix to a value in 0..1")
    photoreal = sum(f.photoreal for f in frames)
    if photoreal_mix > 0 and not photoreal:
        raise ConfigError(f"photoreal_mix is {photoreal_mix} but the training frames have no photoreal (Cycles) "
                          "frames", "render some (dataset photoreal_frames: N) or set photoreal_mix: -1")
    if 0 <= photoreal_mix < 1 and photoreal == len(frames):
        raise ConfigError(f"photoreal_mix is {photoreal_mix} but every training frame is photoreal (no fast-path "
                          "frames)", "add a dataset rendered with render.engine=raster, or set photoreal_mix: -1")


def read_rgb(path: Path) -> np.ndarray:
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ContractError(f"cannot read image {path}", "the dataset is damaged; regenerate it")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


ANY_OBJECT = "*"
"""The object name that stands for every object (training a generic prior: `TrainConfig.any_object`)."""


def instances(annotation: dict, object_name: str, min_visibility: float) -> list[dict]:
    """The DOPE entries of `object_name` (every object's for `ANY_OBJECT`) in one frame's annotation, at least
    `min_visibility` visible."""
    return [o for o in annotation["objects"]
            if object_name in (o["class"], ANY_OBJECT) and o.get("visibility", 1.0) >= min_visibility]


def canonical_instance(obj: dict, intrinsics: dict, cuboid_m: np.ndarray, sym_poses: list[np.ndarray]) -> dict:
    """A DOPE instance entry relabelled with the canonical of its symmetric poses: its projected cuboid is that of
    T_cam_obj @ S for the S `canonical_pose` picks (location in cm, quaternion xyzw, as DOPE JSON stores them)."""
    T = make_T(R_from_quat(np.array(obj["quaternion_xyzw"], float)), np.array(obj["location"], float) / 100.0)
    T_canonical, _ = canonical_pose(T, sym_poses)
    K = np.array([[intrinsics["fx"], 0.0, intrinsics["cx"]], [0.0, intrinsics["fy"], intrinsics["cy"]],
                  [0.0, 0.0, 1.0]])
    return {**obj, "projected_cuboid": project(K, T_canonical, cuboid_m).tolist()}


def affine(image_size: tuple[int, int], input_size: tuple[int, int], rng: np.random.Generator | None,
           aug: AugmentConfig, centre: np.ndarray | None = None, zoom: float = 1.0) -> np.ndarray:
    """2 x 3 map from dataset pixels to network-input pixels, then (with `rng`) zoomed, rotated and shifted.

    Without `centre` the frame is fitted to the input; with it (crop training) the frame is scaled by `zoom` and
    the dataset pixel `centre` lands at the middle of the input."""
    (w, h), (iw, ih) = image_size, input_size
    s, angle, shift = min(iw / w, ih / h), 0.0, np.zeros(2)
    if centre is not None:
        s = zoom
    else:
        centre = np.array([(w - 1) / 2, (h - 1) / 2])
    if rng is not None:
        s *= np.exp(rng.uniform(np.log(aug.scale[0]), np.log(aug.scale[1])))
        angle = rng.uniform(-aug.rotate_deg, aug.rotate_deg)
        shift = rng.uniform(-aug.shift, aug.shift, 2) * (iw, ih)
    M = cv2.getRotationMatrix2D((float(centre[0]), float(centre[1])), angle, s)
    M[:, 2] += ((iw - 1) / 2 - centre[0]) + shift[0], ((ih - 1) / 2 - centre[1]) + shift[1]
    return M


def warp_points(M: np.ndarray, points: np.ndarray) -> np.ndarray:
    return np.asarray(points, dtype=np.float64) @ M[:, :2].T + M[:, 2]


def _noise_background(rng: np.random.Generator, size: tuple[int, int]) -> np.ndarray:
    """Smooth random colour blobs over fine noise: a background no render contains."""
    w, h = size
    cells = rng.integers(2, 12)
    blobs = cv2.resize(rng.uniform(0, 255, (cells, cells, 3)).astype(np.uint8), (w, h), interpolation=cv2.INTER_CUBIC)
    return np.clip(blobs + rng.normal(0, rng.uniform(0, 25), (h, w, 3)), 0, 255).astype(np.uint8)


def photometric(image: np.ndarray, rng: np.random.Generator, aug: AugmentConfig) -> np.ndarray:
    """Colour jitter (brightness, contrast, saturation, hue), blur and noise on an RGB uint8 image."""
    hsv = cv2.cvtColor(image, cv2.COLOR_RGB2HSV).astype(np.float32)
    hsv[..., 0] = (hsv[..., 0] + rng.uniform(-aug.hue_deg, aug.hue_deg) / 2) % 180
    hsv[..., 1] *= 1 + rng.uniform(-aug.saturation, aug.saturation)
    img = cv2.cvtColor(np.clip(hsv, 0, 255).astype(np.uint8), cv2.COLOR_HSV2RGB).astype(np.float32) / 255
    img = img * (1 + rng.uniform(-aug.brightness, aug.brightness))
    img = (img - img.mean()) * (1 + rng.uniform(-aug.contrast, aug.contrast)) + img.mean()
    if rng.random() < aug.blur:
        img = cv2.GaussianBlur(img, (0, 0), rng.uniform(0.5, 1.5))
    img = img + rng.normal(0, rng.uniform(0, aug.noise), img.shape).astype(np.float32)
    return np.clip(img, 0, 1)


class DopeSamples(torch.utils.data.Dataset):
    """(image 3 x H x W in 0..1, beliefs 9 x H/8 x W/8, affinities 16 x H/8 x W/8) of one object's frames.

    With `augment` every item is a new random view of its frame, drawn from (seed, epoch, index) so a run is
    reproducible; call `set_epoch` before each epoch. Without it, frames are only fitted to the input size.
    """

    def __init__(self, frames: list[Frame], object_name: str, cfg: TrainConfig, augment: bool,
                 symmetric: dict[str, tuple[np.ndarray, list[np.ndarray]]] | None = None):
        """`symmetric`: object name -> (its 9 x 3 cuboid keypoints, its symmetric poses) for symmetry-aware
        targets: each instance of such an object is labelled with the canonical one of its equivalent poses
        (`canonical_pose`), so corners the image cannot tell apart never get contradicting labels."""
        self.frames, self.object_name, self.cfg, self.augment = frames, object_name, cfg, augment
        self.symmetric = symmetric
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, index: int):
        cfg, aug = self.cfg, self.cfg.augment
        rng = np.random.default_rng([cfg.seed, self.epoch, index]) if self.augment else None
        frame = self.frames[index]
        annotation = json.loads(frame.annotation.read_text())
        shown = instances(annotation, self.object_name, cfg.min_visibility)
        if self.symmetric:
            intrinsics = annotation["camera_data"]["intrinsics"]
            shown = [canonical_instance(o, intrinsics, *self.symmetric[o["class"]]) if o["class"] in self.symmetric
                     else o for o in shown]
        rgb = read_rgb(frame.image)
        size = (rgb.shape[1], rgb.shape[0])
        centre = None
        if cfg.crop and shown:
            centre = np.array(shown[int(rng.integers(len(shown))) if rng is not None else 0]["projected_cuboid"][8])
        M = affine(size, cfg.input_size, rng, aug, centre, cfg.zoom)
        fill = tuple(int(v) for v in rng.integers(0, 256, 3)) if rng is not None else (127, 127, 127)
        image = cv2.warpAffine(rgb, M, cfg.input_size, flags=cv2.INTER_LINEAR, borderValue=fill)
        if rng is not None and rng.random() < aug.background_swap:
            image = self._swap_background(image, frame, M, rng)
        image = photometric(image, rng, aug) if rng is not None else image.astype(np.float32) / 255
        keypoints, visible = [], []
        for obj in shown:
            keypoints.append(warp_points(M, obj["projected_cuboid"]))
            vis = np.array(obj.get("keypoint_visibility", [1] * 9), bool)
            visible.append(np.ones(9, bool) if cfg.hidden_keypoints else vis)
        map_size = (cfg.input_size[0] // STRIDE, cfg.input_size[1] // STRIDE)
        beliefs, affinities = make_targets(keypoints, visible, map_size, cfg.sigma_cells, cfg.affinity_radius_cells)
        return (torch.from_numpy(np.ascontiguousarray(image.transpose(2, 0, 1))), torch.from_numpy(beliefs),
                torch.from_numpy(affinities))

    def _swap_background(self, image: np.ndarray, frame: Frame, M: np.ndarray, rng: np.random.Generator):
        """Keep the annotated objects (their visible masks), replace the rest by noise or by another frame whose
        own annotated objects are blanked out (an unlabelled copy of the object would teach it to be ignored)."""
        union = _union_mask(frame)
        if union is None:
            return image
        keep = cv2.warpAffine(union, M, self.cfg.input_size, flags=cv2.INTER_NEAREST).astype(bool)
        background = _noise_background(rng, self.cfg.input_size)
        other = self.frames[int(rng.integers(len(self.frames)))]
        other_mask = _union_mask(other)
        if rng.random() < 0.5 and other != frame and other_mask is not None:
            size = self.cfg.input_size
            other_rgb = cv2.resize(read_rgb(other.image), size, interpolation=cv2.INTER_AREA)[:, ::-1]
            other_mask = cv2.resize(other_mask, size, interpolation=cv2.INTER_NEAREST)[:, ::-1].astype(bool)
            background = np.where(other_mask[..., None], background, other_rgb)
        return np.where(keep[..., None], image, background)


def _union_mask(frame: Frame) -> np.ndarray | None:
    """Union of the visible masks of every annotated instance of a frame (uint8 0/1), None without masks."""
    masks = frame.masks()
    if not masks:
        return None
    union = None
    for path in masks:
        mask = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if mask is None or (union is not None and mask.shape != union.shape):
            raise ContractError(f"cannot read the mask {path}, or it has another size than the frame's", _DAMAGED)
        union = mask > 0 if union is None else union | (mask > 0)
    return union.astype(np.uint8)
