"""Pose accuracy metrics of DOPE and PoseCNN: ADD, ADD-S, accuracy at a fraction of the diameter, AUC to 10 cm.

Plain numpy functions over 4 x 4 poses (object -> camera, metres) and N x 3 model points (object frame, metres).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

AUC_MAX_M = 0.10
"""The AUC integrates accuracy over thresholds from 0 to 10 cm (PoseCNN, DOPE)."""


def _apply(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ T[:3, :3].T + T[:3, 3]


def add(T_est: np.ndarray, T_gt: np.ndarray, points: np.ndarray) -> float:
    """ADD: mean distance between the model points under the estimated and the true pose (metres)."""
    return float(np.linalg.norm(_apply(T_est, points) - _apply(T_gt, points), axis=1).mean())


def add_s(T_est: np.ndarray, T_gt: np.ndarray, points: np.ndarray) -> float:
    """ADD-S: mean distance from each estimated model point to the closest true one (symmetric objects)."""
    distances, _ = cKDTree(_apply(T_gt, points)).query(_apply(T_est, points), k=1)
    return float(distances.mean())


def accuracy(errors: np.ndarray, threshold: float) -> float:
    """Fraction of errors below `threshold` (missed detections are infinite errors)."""
    errors = np.asarray(errors, dtype=float)
    return float((errors < threshold).mean()) if errors.size else 0.0


def auc(errors: np.ndarray, max_threshold: float = AUC_MAX_M, steps: int = 1000) -> float:
    """Area under the accuracy-threshold curve for thresholds 0..`max_threshold`, normalised to 0..1."""
    errors = np.asarray(errors, dtype=float)
    if not errors.size:
        return 0.0
    thresholds = np.linspace(0.0, max_threshold, steps + 1)
    return float(np.mean([(errors < t).mean() for t in thresholds]))


def summarize(add_errors: list[float], adds_errors: list[float], diameter_m: float) -> dict:
    """ADD and ADD-S accuracy at 10 % of the diameter, AUC to 10 cm, and the error medians (mm)."""
    a, s = np.asarray(add_errors, float), np.asarray(adds_errors, float)
    return {"instances": int(a.size), "detected": int(np.isfinite(a).sum()),
            "add_accuracy_10pct": accuracy(a, 0.1 * diameter_m), "adds_accuracy_10pct": accuracy(s, 0.1 * diameter_m),
            "add_auc_10cm": auc(a), "adds_auc_10cm": auc(s),
            "add_median_mm": _mm(a), "adds_median_mm": _mm(s),
            "diameter_mm": diameter_m * 1000}


def _mm(errors: np.ndarray) -> float | None:
    """Median error in mm, None when there is none or most instances were missed (JSON has no infinity)."""
    median = float(np.median(errors)) if errors.size else np.inf
    return median * 1000 if np.isfinite(median) else None


# BOP's pose errors (bop_toolkit_lib/pose_error.py) and recall thresholds (BOP 2019-: eval_bop19_pose.py).

MSSD_THRESHOLDS = np.arange(1, 11) * 0.05
"""MSSD thresholds as fractions of the object diameter: 0.05, 0.10, .., 0.50."""
MSPD_THRESHOLDS_PX = np.arange(1, 11) * 5.0
"""MSPD thresholds in pixels for a 640 px wide image: 5, 10, .., 50 (scaled by width / 640)."""


def _symmetries(sym_poses) -> list[np.ndarray]:
    return [np.eye(4)] if sym_poses is None or not len(sym_poses) else [np.asarray(S, float) for S in sym_poses]


def mssd(T_est: np.ndarray, T_gt: np.ndarray, points: np.ndarray, sym_poses=None) -> float:
    """Maximum Symmetry-aware Surface Distance (metres): over the model's symmetries S (4 x 4, identity
    included, as n2d_common.symmetry.symmetric_poses gives; None: no symmetry), the smallest largest
    distance between the model points under T_est and under T_gt @ S."""
    est = _apply(T_est, points)
    return float(min(np.linalg.norm(est - _apply(T_gt @ S, points), axis=1).max() for S in _symmetries(sym_poses)))


def mspd(T_est: np.ndarray, T_gt: np.ndarray, points: np.ndarray, K: np.ndarray, sym_poses=None) -> float:
    """Maximum Symmetry-aware Projection Distance (pixels): as `mssd`, with the distances between the points'
    projections through the 3 x 3 intrinsics K."""
    K = np.asarray(K, dtype=float)
    est = _project(K, T_est, points)
    return float(min(np.linalg.norm(est - _project(K, T_gt @ S, points), axis=1).max()
                     for S in _symmetries(sym_poses)))


def _project(K: np.ndarray, T: np.ndarray, points: np.ndarray) -> np.ndarray:
    p = _apply(T, points) @ K.T
    return p[:, :2] / p[:, 2:3]


def mssd_thresholds(diameter: float) -> np.ndarray:
    """BOP's MSSD thresholds for an object of this diameter (its unit)."""
    return MSSD_THRESHOLDS * float(diameter)


def mspd_thresholds(image_width: int) -> np.ndarray:
    """BOP's MSPD thresholds (pixels) for images of this width."""
    return MSPD_THRESHOLDS_PX * float(image_width) / 640.0


def bop_recall(errors: np.ndarray, thresholds: np.ndarray) -> float:
    """BOP's average recall: the fraction of errors below each threshold, averaged over the thresholds
    (missed detections are infinite errors)."""
    thresholds = np.asarray(thresholds, dtype=float)
    return float(np.mean([accuracy(errors, t) for t in thresholds])) if thresholds.size else 0.0
