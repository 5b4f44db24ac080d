"""The capture sweep: turn the plate through N stops and take one fresh frame at each, resumably.

Hardware-free: the plate is turned by any `Rotator` (the Dynamixel driver, or a ROS action client)
and frames come from any `FrameSource` (a ROS image topic, an OpenCV device or file, the simulator).
A frame is taken only if it was exposed after the plate settled (`grab(after_s=...)`), never a
buffered one. Each view is written atomically and recorded in `<sweep>.json` right after, so a
sweep that stops (fault, Ctrl-C, cancel) keeps what it took and a re-run continues at the next stop.
"""

from __future__ import annotations

import json
import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from n2d_common.camera import Frame
from n2d_common.contracts import atomic_write_json
from n2d_common.errors import Cancelled, ContractError
from n2d_common.images import write_png
from n2d_common.progress import Eta, Progress, ProgressFn, no_progress


class FrameSource(Protocol):
    def grab(self, after_s: float, timeout_s: float) -> Frame:
        """The first frame exposed at or after `after_s`; raises DeviceError after `timeout_s`."""


class Rotator(Protocol):
    def rotate_to(self, angle_rad: float) -> float:
        """Turn the plate to `angle_rad`, wait until it settles, return the reached angle."""


@dataclass
class SweepConfig:
    """One turn of the plate."""

    views: int = 36
    """Stops per revolution."""
    start_angle_rad: float = 0.0
    """Plate angle of the first stop."""
    frame_timeout_s: float = 10.0
    """How long to wait for a fresh frame after the plate settled."""
    first_frame_timeout_s: float = 60.0
    """How long to wait for the camera's first frame (drivers and simulators take a while to start)."""

    def __post_init__(self):
        if self.views < 1:
            raise ValueError("views must be >= 1")
        if self.frame_timeout_s <= 0 or self.first_frame_timeout_s <= 0:
            raise ValueError("frame_timeout_s and first_frame_timeout_s must be > 0")

    def angles(self) -> list[float]:
        return [self.start_angle_rad + 2 * math.pi * i / self.views for i in range(self.views)]


def read_sweep(directory: Path, name: str) -> list[dict]:
    """The view records of sweep `name` in a session directory (empty if it has not started)."""
    path = directory / f"{name}.json"
    if not path.is_file():
        return []
    return json.loads(path.read_text())["views"]


def run_sweep(directory: Path, name: str, cfg: SweepConfig, rotator: Rotator, camera: FrameSource, *,
              progress: ProgressFn = no_progress, cancel: threading.Event | None = None) -> list[dict]:
    """Take the views of sweep `name` ("images" for the object, "empty" for the empty plate) into
    `directory/<name>/NNNN.png`, continuing after the views already recorded. Returns all records."""
    views = read_sweep(directory, name)
    angles = cfg.angles()
    if views and len(views) > len(angles):
        raise ContractError(f"{directory} holds a {name} sweep of more views than {cfg.views}",
                            "re-run with the same number of views, or --overwrite")
    (directory / name).mkdir(parents=True, exist_ok=True)
    if len(views) < len(angles):
        progress(Progress(len(views) / len(angles), "waiting", message="for the camera's first frame"))
        camera.grab(0.0, cfg.first_frame_timeout_s)
    eta = Eta()
    for i in range(len(views), len(angles)):
        if cancel is not None and cancel.is_set():
            raise Cancelled(f"capture cancelled after {i} of {cfg.views} views", "run it again to resume")
        fraction = i / len(angles)
        progress(Progress(fraction, "rotating", eta(fraction), f"{name} view {i + 1}/{cfg.views}", {"view": i}))
        reached = rotator.rotate_to(angles[i])
        settled = time.time()
        progress(Progress(fraction, "grabbing", eta(fraction), f"{name} view {i + 1}/{cfg.views}", {"view": i}))
        frame = camera.grab(settled, cfg.frame_timeout_s)
        file = f"{name}/{i:04d}.png"
        write_png(directory / file, frame.rgb)
        record = {"index": i, "file": file, "angle_cmd_rad": angles[i], "angle_rad": reached,
                  "stamp_s": frame.stamp_s, "settled_s": settled}
        if frame.K is not None:
            record["K"] = np.asarray(frame.K).tolist()
            record["dist"] = [] if frame.dist is None else np.asarray(frame.dist).ravel().tolist()
        views.append(record)
        atomic_write_json(directory / f"{name}.json", {"sweep": name, "views": views})
        progress(Progress((i + 1) / len(angles), "grabbing", eta((i + 1) / len(angles)),
                          f"{name} view {i + 1}/{cfg.views}", {"view": i, "image": frame.rgb}))
    return views
