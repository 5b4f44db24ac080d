"""DOPE inference on an ONNX model: image -> belief and affinity maps -> keypoints -> instances -> PnP poses.

`DopeModel(directory)` loads a DOPE model directory (from `n2d train`); `detect(rgb, K)` returns one `Detection`
per instance found, with `T_cam_obj` (object frame -> OpenCV camera frame, metres). No ROS here: `dope_node`,
`n2d evaluate` and the benchmarks all call this.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from n2d_common.contracts import open_stage
from n2d_common.errors import ConfigError, ContractError
from n2d_common.frames import project
from n2d_dope.config import DetectConfig, RefineConfig
from n2d_dope.export import INPUT, OUTPUTS, session
from n2d_dope.network import INPUT_MULTIPLE
from n2d_dope.pose_refine import Refiner, believable
from n2d_dope.targets import CENTROID, to_image


@dataclass
class Detection:
    """One object instance found in an image."""

    object: str
    """Object (class) name."""
    T_cam_obj: np.ndarray
    """4 x 4 pose: object frame -> OpenCV camera frame, metres."""
    score: float
    """Confidence in 0..1: the summed peak beliefs of the keypoints used, over 9."""
    keypoints_px: np.ndarray
    """9 x 2 image pixels of the keypoints found (DOPE order), NaN where none was found."""
    reprojection_px: float
    """RMS distance between the found keypoints and the cuboid projected with the pose."""
    refine_score: float = float("nan")
    """Agreement of the image with the refined pose's silhouette, 0..1 (NaN: not refined; `n2d_dope.pose_refine`)."""
    source: str = "detected"
    """Where the pose comes from: "detected" (the network, in this frame or, for a track just started, the last
    one) or "tracked" (followed from the previous frame, `n2d_dope.track`)."""


@dataclass
class Timing:
    """Seconds spent per phase of the last `detect` call."""

    preprocess: float = 0.0
    network: float = 0.0
    postprocess: float = 0.0
    refine: float = 0.0


def find_peaks(belief: np.ndarray, threshold: float, smooth_sigma: float) -> np.ndarray:
    """Local maxima of one belief map above `threshold`: rows (x, y, value) in map cells, strongest first.

    Sub-cell position from a parabola through the logarithm of the peak and its 4 neighbours: exact for a
    Gaussian peak (the targets are Gaussians, and smoothing a Gaussian keeps it one)."""
    b = cv2.GaussianBlur(belief, (0, 0), smooth_sigma) if smooth_sigma > 0 else belief
    peaks = (b >= cv2.dilate(b, np.ones((3, 3), np.uint8))) & (b > threshold)
    ys, xs = np.nonzero(peaks)
    logb = np.log(np.clip(np.pad(b, 1, mode="edge"), 1e-6, None))
    out = []
    for y, x in zip(ys, xs):
        c = logb[y + 1, x + 1]
        offsets = []
        for lo, hi in ((logb[y + 1, x], logb[y + 1, x + 2]), (logb[y, x + 1], logb[y + 2, x + 1])):
            curvature = lo - 2 * c + hi
            offsets.append(float(np.clip(0.5 * (lo - hi) / curvature, -1, 1)) if curvature < -1e-9 else 0.0)
        out.append((x + offsets[0], y + offsets[1], float(b[y, x])))
    out.sort(key=lambda p: -p[2])
    return np.array(out, dtype=np.float64).reshape(-1, 3)


def _sample(field2: np.ndarray, x: float, y: float) -> np.ndarray:
    """Bilinear sample of a 2 x h x w field at map coordinates (x, y)."""
    return np.array([cv2.getRectSubPix(f, (1, 1), (float(x), float(y)))[0, 0] for f in field2])


def group_instances(beliefs: np.ndarray, affinities: np.ndarray, cfg: DetectConfig) -> list[np.ndarray]:
    """Per instance a 9 x 3 array (x, y in map cells, belief; NaN where missing): centroid peaks are instances,
    each corner peak joins the centroid its affinity vector points at (within `cfg.affinity_threshold` rad),
    and each instance keeps its strongest corner of each kind."""
    centroids = find_peaks(beliefs[CENTROID], cfg.peak_threshold, cfg.smooth_sigma_cells)[:cfg.max_instances]
    groups = [np.full((9, 3), np.nan) for _ in centroids]
    for g, c in zip(groups, centroids):
        g[CENTROID] = c
    if not groups:
        return []
    for k in range(CENTROID):
        for x, y, value in find_peaks(beliefs[k], cfg.peak_threshold, cfg.smooth_sigma_cells):
            v = _sample(affinities[2 * k:2 * k + 2], x, y)
            if np.linalg.norm(v) < 1e-3:
                continue
            to_centroids = centroids[:, :2] - (x, y)
            cosines = to_centroids @ v / (np.linalg.norm(to_centroids, axis=1) * np.linalg.norm(v) + 1e-9)
            best = int(np.argmax(cosines))
            if np.arccos(np.clip(cosines[best], -1, 1)) > cfg.affinity_threshold:
                continue
            if np.isnan(groups[best][k, 2]) or groups[best][k, 2] < value:
                groups[best][k] = (x, y, value)
    return groups


def solve_pose(points_px: np.ndarray, cuboid_m: np.ndarray, K: np.ndarray,
               inlier_px: float = 0.0) -> tuple[np.ndarray, float] | None:
    """Pose (4 x 4, object -> camera) from the found keypoints (9 x 2, NaN where missing) by SQPnP refined with
    Levenberg-Marquardt, and the RMS reprojection error of the keypoints used; None when fewer than 4 points or
    no solution in front.

    With `inlier_px` > 0 and 5 or more points, keypoints further than that (pixels) from the pose that EPnP-RANSAC
    finds for the most of them are left out first: a corner the network placed on the wrong side of the object
    would otherwise pull the whole pose (OpenCV's RANSAC is seeded the same on every call)."""
    ok = np.isfinite(points_px).all(axis=1)
    if ok.sum() < 4:
        return None
    try:
        return _solve(points_px, cuboid_m, K, ok, inlier_px)
    except cv2.error:  # degenerate keypoints (SQPnP refuses points that nearly coincide): no pose
        return None


def _solve(points_px: np.ndarray, cuboid_m: np.ndarray, K: np.ndarray, ok: np.ndarray,
           inlier_px: float) -> tuple[np.ndarray, float] | None:
    """`solve_pose` on the keypoints `ok` selects (OpenCV may raise on degenerate ones)."""
    if inlier_px > 0 and ok.sum() >= 5:
        found, _, _, inliers = cv2.solvePnPRansac(cuboid_m[ok].astype(np.float64), points_px[ok].astype(np.float64),
                                                  K, None, iterationsCount=100, reprojectionError=inlier_px,
                                                  flags=cv2.SOLVEPNP_EPNP)
        if found and inliers is not None and len(inliers) >= 4:
            keep = np.zeros(len(ok), bool)
            keep[np.flatnonzero(ok)[inliers[:, 0]]] = True
            ok = keep
    obj, img = cuboid_m[ok].astype(np.float64), points_px[ok].astype(np.float64)
    found, rvec, tvec = cv2.solvePnP(obj, img, K, None, flags=cv2.SOLVEPNP_SQPNP)
    if not found:
        return None
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, None, rvec, tvec)
    if tvec[2, 0] <= 0:
        return None
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(rvec)[0]
    T[:3, 3] = tvec[:, 0]
    proj = cv2.projectPoints(obj, rvec, tvec, K, None)[0][:, 0]
    return T, float(np.sqrt(((proj - img) ** 2).sum(1).mean()))


_DAMAGED = "the DOPE model directory is damaged: train it again (n2d train), or restore it"


def read_model_config(directory: Path) -> dict:
    """A DOPE model directory's config.json, checked to hold what detection reads (ContractError otherwise)."""
    path = directory / "config.json"
    try:
        config = json.loads(path.read_text())
        models, cuboid = config["models"], np.asarray(config["cuboid_points_m"], float)
        if not isinstance(models, dict) or not all(isinstance(v, str) for v in models.values()):
            raise ValueError("models must map precisions to ONNX file names")
        if cuboid.shape != (9, 3) or not np.isfinite(cuboid).all():
            raise ValueError(f"cuboid_points_m is not 9 finite points (shape {cuboid.shape})")
        focal = config.get("trained_focal_px", 1.0)
        if isinstance(focal, bool) or not isinstance(focal, (int, float)) or not np.isfinite(focal) or focal <= 0:
            raise ValueError(f"trained_focal_px is {focal!r}, not a number > 0")
        if not isinstance(config["object"], str):
            raise ValueError("object is not a name")
    except OSError as exc:
        raise ContractError(f"cannot read {path}: {exc.strerror or exc}", _DAMAGED) from None
    except (KeyError, TypeError, ValueError) as exc:
        what = f"has no {exc}" if isinstance(exc, KeyError) else f"is malformed ({type(exc).__name__}: {exc})"
        raise ContractError(f"{path} {what}", _DAMAGED) from None
    return config


def _checked_session(path: Path, threads: int):
    """The onnxruntime session of a DOPE network, checked to take an RGB image and give DOPE's maps."""
    if not path.is_file():
        raise ContractError(f"{path} does not exist", _DAMAGED)
    try:
        sess = session(path, threads)
    except Exception as exc:  # onnxruntime's errors (InvalidProtobuf, Fail, ...) share no base class
        raise ContractError(f"onnxruntime cannot load {path} ({type(exc).__name__})", _DAMAGED) from None
    inputs = {i.name: i.shape for i in sess.get_inputs()}
    outputs = {o.name: o.shape for o in sess.get_outputs()}
    expected = {OUTPUTS[0]: 9, OUTPUTS[1]: 16}
    if (list(inputs) != [INPUT] or len(inputs[INPUT]) != 4 or inputs[INPUT][1] != 3
            or any(len(outputs.get(name) or []) != 4 or outputs[name][1] != n for name, n in expected.items())):
        maps = ", ".join(f"{k} N x {n} x h x w" for k, n in expected.items())
        raise ContractError(f"{path} is not a DOPE network: it takes {inputs} and gives {outputs}, not "
                            f"{INPUT} N x 3 x H x W in and {maps} out", _DAMAGED)
    return sess


def merge_detections(detections: list[Detection], K: np.ndarray, cuboid_m: np.ndarray) -> list[list[Detection]]:
    """Detections grouped by instance, best first within a group and groups by their best: the passes of an image
    pyramid find one object several times. Ranked by score / (1 + reprojection_px) (confident keypoints that one
    pose explains); a detection whose projected centre lies within half the smaller projected cuboid of a group's
    first joins that group."""
    ranked = sorted(detections, key=lambda d: -d.score / (1.0 + d.reprojection_px))
    groups: list[tuple[np.ndarray, float, list[Detection]]] = []
    for d in ranked:
        c = project(K, d.T_cam_obj, cuboid_m)
        centre, size = c[8], float(np.ptp(c[:8], axis=0).max())
        for first_centre, first_size, group in groups:
            if np.linalg.norm(centre - first_centre) < 0.5 * min(size, first_size):
                group.append(d)
                break
        else:
            groups.append((centre, size, [d]))
    return [group for _, _, group in groups]


class DopeModel:
    """A DOPE model directory ready to detect its object: the ONNX session and the cuboid."""

    def __init__(self, directory: str | Path, *, precision: str = "fp32", cfg: DetectConfig | None = None,
                 threads: int = 0, refine: RefineConfig | None = None, object_dir: str | Path | None = None):
        self.directory = Path(directory)
        open_stage(self.directory, "dope_model")
        self.config = read_model_config(self.directory)
        if precision not in self.config["models"]:
            raise ConfigError(f"{self.directory} has no {precision} model",
                              f"available: {', '.join(self.config['models'])}")
        self.precision = precision
        self.cfg = cfg or DetectConfig()
        self.name = self.config["object"]
        self.cuboid_m = np.array(self.config["cuboid_points_m"], float)
        self.session = _checked_session(self.directory / self.config["models"][precision], threads)
        self.timing = Timing()
        self.refiner = None
        if refine is not None:
            self.enable_refinement(refine, object_dir)

    def enable_refinement(self, cfg: RefineConfig, object_dir: str | Path | None = None) -> None:
        """Refine every detection from now on (`refine`), against the object's model in `object_dir` (default:
        `object_dir()`); its sparse viewpoint model is cached in the DOPE directory."""
        self.refiner = Refiner(self.object_dir(object_dir), cfg, cache_dir=self.directory)

    def object_dir(self, given: str | Path | None = None) -> Path:
        """The object's model directory: `given`, the copy kept in the DOPE directory, or the one the network was
        trained on."""
        kept = self.config.get("object_model")
        path = Path(given or (self.directory / kept if kept else self.config.get("model_dir")) or "")
        if not (path / "mesh.obj").is_file():
            raise ConfigError(f"no object model at {path} for refinement",
                              "pass the object's model directory (from n2d reconstruct), or turn refinement off")
        return path

    def scale_for(self, K: np.ndarray) -> float:
        """Camera image -> network input resize factor (`cfg.net_scale`, or the trained focal over the camera's)."""
        if self.cfg.net_scale > 0:
            return self.cfg.net_scale
        return float(self.config["trained_focal_px"]) / float(np.sqrt(K[0, 0] * K[1, 1]))

    def maps(self, rgb: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
        """Belief (9 x h x w) and affinity (16 x h x w) maps of an RGB uint8 image resized by `scale`."""
        t0 = time.perf_counter()
        h, w = rgb.shape[:2]
        size = (max(1, round(w * scale)), max(1, round(h * scale)))
        img = rgb if size == (w, h) else cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
        padded = np.zeros((-(-size[1] // INPUT_MULTIPLE) * INPUT_MULTIPLE,
                           -(-size[0] // INPUT_MULTIPLE) * INPUT_MULTIPLE, 3), np.float32)
        padded[:size[1], :size[0]] = img.astype(np.float32) / 255.0
        x = np.ascontiguousarray(padded.transpose(2, 0, 1)[None])
        t1 = time.perf_counter()
        belief, affinity = self.session.run(list(OUTPUTS), {INPUT: x})
        self.timing.preprocess, self.timing.network = t1 - t0, time.perf_counter() - t1
        return belief[0], affinity[0]

    def detect(self, rgb: np.ndarray, K: np.ndarray) -> list[Detection]:
        """Instances of the object in an RGB uint8 image taken with intrinsics K (3 x 3, undistorted): the network
        at each scale of `cfg.scales`, one detection per instance (`merge_detections`), refined when refinement
        is on (the best-ranked detection of an instance whose refined pose is believable)."""
        base = self.scale_for(K)
        candidates, preprocess, network, postprocess = [], 0.0, 0.0, 0.0
        for factor in self.cfg.scales:
            scale = base * factor
            beliefs, affinities = self.maps(rgb, scale)
            preprocess, network = preprocess + self.timing.preprocess, network + self.timing.network
            t0 = time.perf_counter()
            candidates += self._poses(beliefs, affinities, scale, K)
            postprocess += time.perf_counter() - t0
        t0 = time.perf_counter()
        instances = merge_detections(candidates, K, self.cuboid_m)[: self.cfg.max_instances]
        t1 = time.perf_counter()
        self.timing.preprocess, self.timing.network, self.timing.postprocess = preprocess, network, \
            postprocess + t1 - t0
        if self.refiner is None:
            detections = [group[0] for group in instances]
        else:
            detections = []
            for group in instances:
                refined = next((r for r in (self.refine(rgb, K, c) for c in group) if r is not None), None)
                if refined is not None:
                    detections.append(refined)
        self.timing.refine = time.perf_counter() - t1
        return detections

    def _poses(self, beliefs: np.ndarray, affinities: np.ndarray, scale: float, K: np.ndarray) -> list[Detection]:
        """The instances of one pass's maps (network input = camera image resized by `scale`) with their poses."""
        detections = []
        for group in group_instances(beliefs, affinities, self.cfg):
            found = np.isfinite(group[:, 2])
            if found.sum() < self.cfg.min_keypoints:
                continue
            # map cell -> network-input pixel -> camera-image pixel (pixel centres: (u + 0.5) / s - 0.5)
            points = (to_image(group[:, :2]) + 0.5) / scale - 0.5
            inlier_px = self.cfg.ransac_px / scale
            solved = solve_pose(points, self.cuboid_m, K, inlier_px)
            if solved is None:
                continue
            T, error = solved
            if inlier_px > 0 and np.sum(np.linalg.norm(project(K, T, self.cuboid_m) - points, axis=1) < inlier_px) \
                    < self.cfg.min_inliers:
                continue
            detections.append(Detection(self.name, T, float(np.nansum(group[:, 2]) / 9), points, error))
        return detections

    def refine(self, rgb: np.ndarray, K: np.ndarray, detection: Detection) -> Detection | None:
        """The detection with its pose refined against the image, or None when the refined pose is not believable
        (`n2d_dope.pose_refine.believable`)."""
        refined = self.refiner(rgb, K, detection.T_cam_obj)
        if not believable(refined, self.refiner.cfg):
            return None
        detection.T_cam_obj, detection.refine_score = refined.T_cam_obj, refined.score
        return detection
