"""The capture-session contract: `transforms.json` (nerfstudio's format) and its reader.

A session directory holds `images/NNNN.png`, `masks/NNNN.png`, `transforms.json`, `capture.json`,
`contact_sheet.png` and `n2d.json`. `transforms.json` follows nerfstudio's `nerfstudio_dataparser`
field names (camera_model, fl_x, fl_y, cx, cy, w, h, k1, k2, p1, p2, k3, orientation_override,
frames[].file_path, frames[].mask_path, frames[].transform_matrix); cx, cy follow its pixel-edge
convention (OpenCV + 0.5). Each transform_matrix is camera-to-world, i.e.
T_turntable_cam in the metric, gravity-aligned, plate-attached turntable frame, with the camera
axes in nerfstudio's OpenGL convention (x right, y up, z backwards); `T_cam_opencv` converts.
A session of several placements (the object swept, turned over, and swept again) marks each frame with
`n2d_placement` (0, 1, ..; absent: 0), and each placement's transform_matrix is in that placement's own
turntable frame: the reconstruction registers the placements to the first. A one-placement session has
no such field, so its files are unchanged.
A simulated session may also hold `truth/images/NNNN.png`, the noise-free render of each view: the
reconstruction report scores held-out views against it too (no real camera has one).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from n2d_common.contracts import open_stage
from n2d_common.errors import ContractError

PLACEMENT_KEY = "n2d_placement"
"""The transforms.json frame field holding the frame's placement index (absent: 0)."""
PIXEL_EDGE = 0.5
"""nerfstudio and COLMAP put pixel centres at +0.5, OpenCV at integers: cx_nerfstudio = cx_opencv + 0.5."""
TRUTH_DIR = "truth"
"""Optional session subdirectory: the noise-free image of each view under the image's own relative path."""
OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
"""Right-multiply a camera-to-world pose with OpenCV camera axes to get OpenGL camera axes (and back)."""


def transforms_json(K: np.ndarray, dist: np.ndarray | None, width: int, height: int,
                    frames: list[tuple[str, str | None, np.ndarray]], placements: list[int] | None = None) -> dict:
    """nerfstudio transforms.json content; `frames` holds (image file, mask file or None, T_turntable_cam
    with OpenCV camera axes), paths relative to the session directory; `placements`, one per frame, the
    placement index of each (None: one placement, no field written)."""
    d = np.zeros(5) if dist is None or len(dist) == 0 else np.asarray(dist, dtype=float).ravel()
    d = np.pad(d, (0, max(0, 5 - len(d))))
    out = {
        "camera_model": "OPENCV",
        "fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]),
        "cx": float(K[0, 2]) + PIXEL_EDGE, "cy": float(K[1, 2]) + PIXEL_EDGE,
        "w": int(width), "h": int(height),
        "k1": float(d[0]), "k2": float(d[1]), "p1": float(d[2]), "p2": float(d[3]), "k3": float(d[4]),
        "n2d_frame": "turntable: metres, origin at the plate centre on its top surface, Z up the rotation axis",
        "n2d_convention": "transform_matrix = camera-to-world (T_turntable_cam), OpenGL camera axes "
                          "(x right, y up, z back); cx, cy with pixel centres at +0.5 (nerfstudio, COLMAP): "
                          "OpenCV's cx is cx - 0.5",
        "orientation_override": "none",
        "frames": [],
    }
    for i, (image, mask, T) in enumerate(frames):
        frame = {"file_path": image, "transform_matrix": (np.asarray(T) @ OPENGL_FROM_OPENCV).tolist()}
        if mask is not None:
            frame["mask_path"] = mask
        if placements is not None and any(placements):
            frame[PLACEMENT_KEY] = int(placements[i])
        out["frames"].append(frame)
    return out


@dataclass
class SessionView:
    """One view of a capture session."""

    image: Path
    mask: Path | None
    T_turntable_cam: np.ndarray | None
    """4x4 camera pose (OpenCV camera axes) in the turntable frame, metres; None where the file has none."""
    truth: Path | None = None
    """The view's noise-free image (simulated sessions only), else None."""
    placement: int = 0
    """The placement the view belongs to (0: the first; its pose is in that placement's turntable frame)."""


@dataclass
class Session:
    """A complete capture session, as the reconstruction stage reads it."""

    directory: Path
    K: np.ndarray
    dist: np.ndarray
    width: int
    height: int
    views: list[SessionView]
    manifest: dict

    @property
    def placements(self) -> int:
        """How many placements the session holds (1 for a turntable sweep of the object standing one way)."""
        return 1 + max((v.placement for v in self.views), default=0)


def read_session(directory: str | Path) -> Session:
    """Open a complete capture session (refusing partial or foreign directories with a hint).

    Raises ContractError for a transforms.json that cannot be read, lacks a field or holds a value no camera has
    (a focal length that is not a finite number > 0, a pose that is not a finite 4 x 4 matrix)."""
    directory = Path(directory)
    manifest = open_stage(directory, "capture_session")
    path = directory / "transforms.json"
    try:
        t = json.loads(path.read_text())
        K = np.array([[_number(t, "fl_x"), 0.0, _number(t, "cx") - PIXEL_EDGE],
                      [0.0, _number(t, "fl_y"), _number(t, "cy") - PIXEL_EDGE], [0.0, 0.0, 1.0]])
        dist = np.array([_number(t, k, 0.0) for k in ("k1", "k2", "p1", "p2", "k3")])
        width, height = _number(t, "w"), _number(t, "h")
        if min(K[0, 0], K[1, 1]) <= 0 or width != int(width) or height != int(height) or min(width, height) < 1:
            raise ValueError("focal lengths and image size must be positive (the size whole numbers)")
        frames = t["frames"]
        if not isinstance(frames, list) or not frames:
            raise ValueError("frames is not a non-empty list")
        views = [_view(directory, f) for f in frames]
        present = {v.placement for v in views}
    except OSError as exc:
        raise ContractError(f"cannot read {path}: {exc.strerror or exc}", _DAMAGED) from None
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        what = f"has no {exc}" if isinstance(exc, KeyError) else f"is malformed ({exc})"
        raise ContractError(f"{path} {what}", _DAMAGED) from None
    if present != set(range(len(present))):
        raise ContractError(f"{path} has frames of placements {sorted(present)}",
                            f"placements are numbered 0, 1, .. without gaps ({PLACEMENT_KEY})")
    return Session(directory, K, dist, int(width), int(height), views, manifest)


_DAMAGED = "the session is damaged: capture it again, or restore transforms.json"


def _number(t: dict, key: str, default: float | None = None) -> float:
    """The finite number `t[key]` (ValueError naming it otherwise; KeyError when it is missing without a default)."""
    value = t[key] if default is None else t.get(key, default)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise ValueError(f"{key} is {value!r}, not a finite number")
    return float(value)


def _view(directory: Path, f: dict) -> SessionView:
    image, mask = f["file_path"], f.get("mask_path")
    if not isinstance(image, str) or not (mask is None or isinstance(mask, str)):
        raise ValueError(f"a frame's file_path or mask_path is not a path: {image!r}, {mask!r}")
    T = None
    if "transform_matrix" in f:
        T = np.asarray(f["transform_matrix"], dtype=float)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise ValueError(f"the transform_matrix of {image} is not a finite 4 x 4 matrix")
        T = T @ OPENGL_FROM_OPENCV
    placement = f.get(PLACEMENT_KEY, 0)
    if isinstance(placement, bool) or not isinstance(placement, int) or placement < 0:
        raise ValueError(f"the {PLACEMENT_KEY} of {image} is {placement!r}, not a placement number 0, 1, ..")
    return SessionView(directory / image, directory / mask if mask is not None else None, T,
                       _existing(directory / TRUTH_DIR / image), placement)


def _existing(path: Path) -> Path | None:
    return path if path.is_file() else None
