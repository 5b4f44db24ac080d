"""Benchmark of a whole capture session on the simulator: sweep and processing times, pose, mask and focal errors.

    python benchmarks/capture.py [--views 36] [--object bottle] [--calibrate] [--out /tmp/session]

Runs what `n2d capture` runs: the servo emulator (its own process, on a pty) driven by the real
`Turntable` driver, `SimCamera` frames (640x480, sensor noise) at the plate's true angle, `capture()`
twice (empty plate, then the object). Each view's true plate angle and exact mask are recorded as it
is grabbed. Prints the wall time of both sweeps and of processing (poses + masks); the camera pose
error in the plate-attached turntable frame, split by where the pose came from (the servo angle and
the axis fitted over the sweep, the default; the view's own board pose with `--board-poses`; the servo
angle alone where the board is hidden); the mask IoU against the exact masks; and with `--calibrate` the
error of the focal length calibrated from the board. With `--out` the session (contact_sheet.png
included) is kept there, else it goes to a temporary directory.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from n2d_capture.capture import CaptureConfig, capture
from n2d_capture.masks import iou
from n2d_capture.sweep import SweepConfig
from n2d_capture.turntable import Turntable, TurntableConfig
from n2d_common.camera import Frame
from n2d_common.formats.session import read_session
from n2d_common.frames import inv_T, rot_z
from n2d_common.images import read_png
from n2d_sim.camera import SimCamera
from n2d_sim.frame_source import SimFrameSource
from n2d_sim.servo import ServoControl
from n2d_sim.world import SimWorldConfig, T_cam_turntable
from table import print_table

GOALS = {"rotation_deg": 0.1, "translation_mm": 1.0, "iou": 0.98, "focal_pct": 0.5}
"""Rotation and translation: median error; IoU: mean; focal: absolute error."""


class _Recording:
    """A frame source that remembers the true plate angle and exact mask of every frame it hands out, by
    the frame's stamp (the sweep may grab frames it does not keep, e.g. to wait for the camera)."""

    def __init__(self, source: SimFrameSource):
        self.source = source
        self.truth: dict[float, tuple[float, np.ndarray]] = {}

    def grab(self, after_s: float, timeout_s: float) -> Frame:
        frame = self.source.grab(after_s, timeout_s)
        self.truth[frame.stamp_s] = (self.source.last.angle_rad, self.source.last.mask)
        return frame


@contextmanager
def _servo_emulator() -> Iterator[tuple[str, ServoControl]]:
    """A standalone servo emulator process: (serial port, control client). In a process of its own it
    answers in time while this one renders and computes."""
    with tempfile.TemporaryDirectory(prefix="n2d-servo-") as tmp:  # short path: AF_UNIX names are limited
        link, socket_path = Path(tmp) / "tty", Path(tmp) / "ctl"
        proc = subprocess.Popen([sys.executable, "-m", "n2d_sim.servo", "--link", str(link),
                                 "--control", str(socket_path)], stdout=subprocess.DEVNULL)
        try:
            control = ServoControl(socket_path)
            control.wait_ready(timeout_s=30)
            yield str(link), control
        finally:
            proc.terminate()
            proc.wait(timeout=10)


def _errors(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(rotation deg, translation mm) between two 4x4 poses."""
    R = T_est[:3, :3].T @ T_true[:3, :3]
    return (math.degrees(math.acos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))),
            1000 * float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3])))


def _median_max(values: list[float], unit: str, digits: int) -> str:
    return f"{np.median(values):.{digits}f} / {max(values):.{digits}f} {unit}" if values else "-"


def _median_met(values: list[float], limit: float) -> str:
    """Whether the median of `values` is at most `limit` ("" when there are none)."""
    return "" if not values else ("yes" if np.median(values) <= limit else "NO")


def run(session: Path, world: SimWorldConfig, cfg: CaptureConfig, overwrite: bool) -> list[tuple[str, str, str, str]]:
    """Capture and process one session into `session`; returns the table rows (metric, value, goal, met)."""
    with _servo_emulator() as (port, control):
        # More retries than the default 3: on a loaded machine the emulator may miss the SDK's 34 ms window.
        table_cfg = TurntableConfig(port=port, velocity_limit_rad_s=4.0, acceleration_rad_s2=20.0,
                                    settle_time_s=0.05, retries=10)
        with SimCamera(world) as camera, Turntable(table_cfg) as table:
            source = SimFrameSource(camera, lambda: control.state()["plate_rad"])
            source.object_visible = False
            t0 = time.perf_counter()
            capture(session, cfg, table, source, empty_plate=True, overwrite=overwrite)
            empty_s = time.perf_counter() - t0
            source.object_visible = True
            recording = _Recording(source)
            t0 = time.perf_counter()
            capture(session, cfg, table, recording)
            object_and_process_s = time.perf_counter() - t0

    info = json.loads((session / "capture.json").read_text())
    process_s = info["process_s"]
    views = read_session(session).views
    T_cam_tt = T_cam_turntable(world)
    errors: dict[str, list[tuple[float, float]]] = {"axis": [], "board": [], "servo": []}
    ious = []
    for view, record in zip(views, info["views"], strict=True):
        angle, mask = recording.truth[record["stamp_s"]]
        truth = inv_T(T_cam_tt @ rot_z(angle))
        errors[record["pose_source"]].append(_errors(view.T_turntable_cam, truth))
        ious.append(iou(read_png(view.mask) > 0, mask))

    rows = [("views, object, size", f"{len(views)}, {world.object}, {world.width}x{world.height}", "", ""),
            ("empty-plate sweep", f"{empty_s:.1f} s", "", ""),
            ("object sweep", f"{object_and_process_s - process_s:.1f} s", "", ""),
            ("processing (poses + masks)", f"{process_s:.1f} s", "", "")]
    titles = {"axis": "views posed from the fitted axis", "board": "views posed from their board",
              "servo": "views posed from the servo angle alone"}
    for source_name, errs in errors.items():
        rot, trans = [e[0] for e in errs], [e[1] for e in errs]
        rows += [(titles[source_name], str(len(errs)), "", ""),
                 ("  rotation error, median / max", _median_max(rot, "deg", 3),
                  f"<= {GOALS['rotation_deg']} deg median", _median_met(rot, GOALS["rotation_deg"])),
                 ("  translation error, median / max", _median_max(trans, "mm", 2),
                  f"<= {GOALS['translation_mm']} mm median",
                  _median_met(trans, GOALS["translation_mm"]))]
    rows.append(("mask IoU, mean / min", f"{np.mean(ious):.4f} / {min(ious):.4f}", f">= {GOALS['iou']} mean",
                 "yes" if np.mean(ious) >= GOALS["iou"] else "NO"))
    if cfg.intrinsics == "calibrate":
        focal_pct = 100 * (info["intrinsics"]["K"][0][0] / world.focal_px - 1)
        rows.append(("calibrated focal error", f"{focal_pct:+.3f} % (rms {info['intrinsics']['rms_px']:.3f} px)",
                     f"within {GOALS['focal_pct']} %", "yes" if abs(focal_pct) <= GOALS["focal_pct"] else "NO"))
    else:
        rows.append(("intrinsics", "from CameraInfo (exact)", "", ""))
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=36, help="views around one turn")
    parser.add_argument("--object", default="box", help="sample object (box, bottle) or model directory")
    parser.add_argument("--calibrate", action="store_true",
                        help="calibrate the focal length from the board (intrinsics: calibrate) instead of CameraInfo")
    parser.add_argument("--board-poses", action="store_true", help="pose each view from its own board pose "
                        "(pose_from: board) instead of the fitted axis")
    parser.add_argument("--out", type=Path, help="keep the session here (default: a temporary directory)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing session at --out")
    args = parser.parse_args(argv)
    world = SimWorldConfig(object=args.object)
    cfg = CaptureConfig(sweep=SweepConfig(views=args.views),
                        intrinsics="calibrate" if args.calibrate else "camera_info",
                        pose_from="board" if args.board_poses else "axis")
    with tempfile.TemporaryDirectory(prefix="n2d-bench-capture-") as tmp:
        session = args.out.absolute() if args.out else Path(tmp) / "session"
        rows = run(session, world, cfg, args.overwrite)
    print_table("Capture benchmark (simulator; errors against its ground truth)", rows,
                ("metric", "value", "goal", "met"))
    if args.out:
        print(f"session: {session} (contact sheet: {session / 'contact_sheet.png'})")


if __name__ == "__main__":
    main()
