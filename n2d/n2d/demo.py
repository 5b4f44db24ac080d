"""`n2d demo`: the main job on the embedded default world (simulated servo + camera + a sample object).

Today it brings up the simulated world, turns the plate through the real Dynamixel driver
(`dynamixel_sdk` on the emulated servo's pty), takes a fresh camera frame at each stop, checks the
driver's angle against the simulator's ground truth, and writes a run directory with the frames
and `contact_sheet.png`. The later stages (reconstruct, dataset, DOPE) join it as they land.
"""

from __future__ import annotations

import math
import os
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from n2d_common.config import to_dict
from n2d_common.contracts import atomic_write_json, read_manifest, stage_output
from n2d_common.errors import DeviceError
from n2d_common.images import contact_sheet, draw_mask_outline, write_png
from n2d_common.progress import Progress, ProgressFn, no_progress


@dataclass
class DemoConfig:
    """What `n2d demo` runs."""

    object: str = "box"
    """Sample object (box, bottle) or a model directory."""
    views: int = 12
    """Turntable stops in the sweep."""
    width: int = 640
    """Camera image width (px)."""
    height: int = 480
    """Camera image height (px)."""
    focal_px: float = 600.0
    """Camera focal length (px); scale it with the image size."""
    velocity_rad_s: float = 1.5
    """Plate profile velocity during the sweep."""
    domain_id: int = -1
    """ROS_DOMAIN_ID of the private simulated world; -1: derived from the process id."""
    startup_timeout_s: float = 180.0
    """How long to wait for the simulated world to come up (first render includes scene building)."""
    extra_sim_args: dict = field(default_factory=dict)
    """Further `n2d launch sim` arguments (name -> value)."""

    def __post_init__(self):
        if self.views < 1:
            raise ValueError("views must be >= 1")
        if self.width < 32 or self.height < 32:
            raise ValueError("width and height must be >= 32 px")
        if self.velocity_rad_s <= 0:
            raise ValueError("velocity_rad_s must be > 0")


def _wait_for_path(path: Path, timeout_s: float, launch) -> None:
    deadline = time.monotonic() + timeout_s
    while not path.exists():
        if launch.dead():
            name, code = launch.dead()[0]
            raise DeviceError(f"the simulated world failed to start ({name} exited with code {code})",
                              "see its log lines above")
        if time.monotonic() > deadline:
            raise DeviceError(f"the simulated servo did not appear at {path} within {timeout_s:.0f} s")
        time.sleep(0.1)


def run_demo(out: Path, cfg: DemoConfig, *, overwrite: bool = False, progress: ProgressFn = no_progress,
             log=print) -> dict:
    """Run the demo into the run directory `out` and return its summary (also written to summary.json)."""
    from n2d.launch_description import load
    from n2d.launcher import Launch
    from n2d_capture.turntable import Turntable, TurntableConfig
    from n2d_common.ros import background_node, ros_environment
    from n2d_sim.ros_client import SimCameraClient

    done = read_manifest(out) if out.is_dir() else None
    if done and done.get("complete") and done["kind"] == "run" and not overwrite:
        log(f"{out} is complete already (pass --overwrite to run again)")
        return done["extra"]

    t_start = time.monotonic()
    domain = cfg.domain_id if cfg.domain_id >= 0 else 1 + os.getpid() % 100
    env = ros_environment(domain, env=dict(os.environ))
    os.environ.update(env)
    tmp = Path(tempfile.mkdtemp(prefix="n2d_demo_"))
    sim_args = {"object": cfg.object, "port": str(tmp / "ttyDXL"), "control": str(tmp / "servo.ctl"),
                "width": str(cfg.width), "height": str(cfg.height), "focal_px": str(cfg.focal_px),
                **cfg.extra_sim_args}
    with stage_output(out, "run", overwrite=overwrite, config=to_dict(cfg)) as writer, \
            Launch(load("sim"), sim_args, env=env, log=lambda line: None) as world:
        frames_dir = writer.path / "frames"
        frames_dir.mkdir(exist_ok=True)
        progress(Progress(0.0, "starting", message="simulated world: servo emulator + camera"))
        _wait_for_path(Path(sim_args["port"]), cfg.startup_timeout_s, world)
        records, sheet, labels = [], [], []
        with background_node("n2d_demo") as node:
            client = SimCameraClient(node)
            table = TurntableConfig(port=sim_args["port"], velocity_limit_rad_s=cfg.velocity_rad_s)
            with Turntable(table) as turntable:
                # The first frame also waits for the renderer to build its scene.
                client.next_frame(time.time(), timeout_s=cfg.startup_timeout_s)
                for i in range(cfg.views):
                    target = 2 * math.pi * i / cfg.views
                    progress(Progress(i / cfg.views, "rotating", message=f"view {i + 1}/{cfg.views}"))
                    reached = turntable.rotate_to(target)
                    settled = time.time()
                    progress(Progress((i + 0.5) / cfg.views, "grabbing", message=f"view {i + 1}/{cfg.views}"))
                    obs = client.next_frame(settled)
                    truth = _plate_angle(obs.T_cam_obj, records[0]["T_cam_obj"] if records else None)
                    name = f"{i:04d}.png"
                    write_png(frames_dir / name, obs.rgb)
                    write_png(frames_dir / f"{i:04d}_mask.png", obs.mask.astype(np.uint8) * 255)
                    records.append({"file": f"frames/{name}", "target_rad": target, "driver_rad": reached,
                                    "true_delta_rad": truth, "stamp": obs.stamp_s,
                                    "T_cam_obj": obs.T_cam_obj.tolist()})
                    sheet.append(draw_mask_outline(obs.rgb, obs.mask, thickness=2))
                    labels.append(f"{math.degrees(reached):6.1f} deg")
            progress(Progress(1.0, "writing"))
        write_png(writer.path / "contact_sheet.png", contact_sheet(sheet, labels))
        errors = [abs(_wrap(r["driver_rad"] - records[0]["driver_rad"] - r["true_delta_rad"])) for r in records]
        summary = {"views": len(records), "seconds": round(time.monotonic() - t_start, 1),
                   "max_driver_vs_truth_deg": math.degrees(max(errors)), "K": client.K.tolist(),
                   "frames": records}
        atomic_write_json(writer.path / "frames.json", summary)
        writer.finish(config=to_dict(cfg), extra={k: v for k, v in summary.items() if k != "frames"})
    return summary


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


def _plate_angle(T_cam_obj: np.ndarray, T_cam_obj0: np.ndarray | None) -> float:
    """Rotation of the object about its own Z axis since the first frame, from ground-truth poses."""
    if T_cam_obj0 is None:
        return 0.0
    R = np.asarray(T_cam_obj0)[:3, :3].T @ T_cam_obj[:3, :3]
    return math.atan2(R[1, 0], R[0, 0])

