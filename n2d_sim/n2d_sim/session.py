"""Capture sessions rendered by the simulator with its exact poses and masks (the ground truth).

The capture stage estimates poses from the board and masks by segmentation; this writes the same
session contract from what the simulator knows exactly, so the reconstruction stage can be tested
and measured on its own. The object's ground-truth pose in the session's turntable frame (the plate
frame, whose X axis the board fixes at the first view) is `T_turntable_obj`.

    python -m n2d_sim.session OUT [--views 36] [--object bottle] [--width 640 --height 480] [--samples 64]

The CLI renders at `CONVERGED_SAMPLES` per pixel, not the live camera's 4: a 4-sample frame (denoised)
differs from a converged render of the same view by 30-32 dB PSNR on the object (`benchmarks/sim_camera.py
--reference-samples 256`), Monte-Carlo noise and denoiser artefacts that change from view to view. No 3-D
model can reproduce those, so a session meant to measure reconstruction quality must not carry them: a real
camera's frames differ only by sensor noise, which the photos get on top.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from n2d_common.contracts import atomic_write_json, stage_output
from n2d_common.formats.session import TRUTH_DIR, transforms_json
from n2d_common.frames import inv_T, rot_z
from n2d_common.images import write_png
from n2d_common.progress import Progress, ProgressFn, no_progress
from n2d_sim import world as sim_world
from n2d_sim.camera import SimCamera
from n2d_sim.world import SimWorldConfig, T_plate_obj, object_dir

CONVERGED_SAMPLES = 64
"""Samples per pixel of sessions rendered to measure reconstruction: 41 dB PSNR from a 256-sample render of
the box (4 samples: 30-32 dB)."""


@dataclass
class GroundTruth:
    """Where the simulated object stands in a session's turntable frame."""

    model_dir: Path
    """The object's model directory (mesh.obj, models_info.json)."""
    T_turntable_obj: np.ndarray
    """4x4 pose of the model frame in the turntable frame, metres."""


def ground_truth(world: SimWorldConfig) -> GroundTruth:
    """The object of `world` as it stands on the plate at plate angle 0 (the session's turntable frame)."""
    return GroundTruth(object_dir(world), T_plate_obj(world))


def render_session(out: str | Path, world: SimWorldConfig, views: int, *, noise: bool = True, seed: int = 0,
                   overwrite: bool = False, progress: ProgressFn = no_progress) -> GroundTruth:
    """Render `views` plate angles evenly over a turn into the capture session `out`; returns the truth."""
    angles = np.arange(views) * 2 * math.pi / views
    rng = np.random.default_rng(seed)
    with stage_output(out, "capture_session", overwrite=overwrite, resume=False, config=None) as writer:
        frames = []
        with SimCamera(world) as camera:
            for i, angle in enumerate(angles):
                frame = camera.render(float(angle))
                image, mask = f"images/{i:04d}.png", f"masks/{i:04d}.png"
                write_png(writer.path / image, camera.noisy(frame.rgb, rng) if noise else frame.rgb)
                if noise:
                    write_png(writer.path / TRUTH_DIR / image, frame.rgb)
                write_png(writer.path / mask, frame.mask.astype(np.uint8) * 255)
                frames.append((image, mask, inv_T(frame.T_cam_turntable @ rot_z(float(angle)))))
                progress(Progress((i + 1) / views, "rendering", message=f"view {i + 1}/{views}"))
        atomic_write_json(writer.path / "transforms.json",
                          transforms_json(sim_world.K(world), None, world.width, world.height, frames))
        atomic_write_json(writer.path / "capture.json", {
            "board": world.board.to_dict(), "pose_source": "simulator ground truth",
            "render": {"samples": world.samples, "denoiser": world.denoiser},
            "views": [{"index": i, "file": f[0], "mask": f[1], "angle_rad": float(a)}
                      for i, (f, a) in enumerate(zip(frames, angles))]})
        writer.finish(extra={"views": views, "simulated": True})
    return ground_truth(world)


def small_world(object_name: str = "box", width: int = 160, height: int = 120, **overrides) -> SimWorldConfig:
    """A fast simulator world for tests: a small image with the focal length scaled to keep the framing."""
    base = SimWorldConfig(object=object_name)
    return replace(base, width=width, height=height, focal_px=base.focal_px * width / base.width, samples=2,
                   background_samples=2, clutter=False, **overrides)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--views", type=int, default=36)
    parser.add_argument("--object", default="box")
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--samples", type=int, default=CONVERGED_SAMPLES, help="Cycles samples per pixel")
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args(argv)
    if args.views < 1:
        parser.error("--views must be >= 1")
    try:
        world = SimWorldConfig(object=args.object, width=args.width, height=args.height,
                               focal_px=SimWorldConfig().focal_px * args.width / 640, samples=args.samples)
    except ValueError as exc:
        parser.error(str(exc))
    render_session(args.out, world, args.views, overwrite=args.overwrite)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
