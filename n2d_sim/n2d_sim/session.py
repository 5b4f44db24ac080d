"""Capture sessions rendered by the simulator with its exact poses and masks (the ground truth).

The capture stage estimates poses from the board and masks by segmentation; this writes the same
session contract from what the simulator knows exactly, so the reconstruction stage can be tested
and measured on its own. The object's ground-truth pose in the session's turntable frame (the plate
frame, whose X axis the board fixes at the first view) is `T_turntable_obj`.

    python -m n2d_sim.session OUT [--views 36] [--object bottle] [--width 640 --height 480] [--samples 64]
                                  [--placements 2]

A session of two placements sweeps the object, turns it over (`SECOND_PLACEMENT_DEG`, its
`SimWorldConfig.placement_deg`) and sweeps it again; each placement's poses are in its own turntable
frame, and the truth holds the object's pose in each.

The CLI renders at `CONVERGED_SAMPLES` per pixel, not the live camera's 4: a 4-sample frame (denoised)
differs from a converged render of the same view by 30-32 dB PSNR on the object (`benchmarks/sim_camera.py
--reference-samples 256`), Monte-Carlo noise and denoiser artefacts that change from view to view. No 3-D
model can reproduce those, so a session meant to measure reconstruction quality must not carry them: a real
camera's frames differ only by sensor noise, which the photos get on top.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from n2d_common.contracts import atomic_write_json, stage_output
from n2d_common.formats.session import TRUTH_DIR, transforms_json
from n2d_common.frames import inv_T, rot_z, transform_points
from n2d_common.images import write_png
from n2d_common.progress import Progress, ProgressFn, no_progress
from n2d_sim import world as sim_world
from n2d_sim.camera import SimCamera
from n2d_sim.world import SimWorldConfig, T_plate_obj, model_vertices, object_dir

CONVERGED_SAMPLES = 64
"""Samples per pixel of sessions rendered to measure reconstruction: 41 dB PSNR from a 256-sample render of
the box (4 samples: 30-32 dB)."""
SECOND_PLACEMENT_DEG: dict[str, tuple[float, float, float]] = {
    "box": (90.0, 0.0, 0.0), "bottle": (90.0, 0.0, 0.0), "mug": (90.0, 0.0, 0.0), "cube_plain": (90.0, 0.0, 0.0),
    "can": (90.0, 0.0, 0.0), "bracket": (0.0, 90.0, 0.0), "remote": (0.0, 180.0, 0.0), "spray": (90.0, 0.0, 0.0),
    "gear": (180.0, 0.0, 0.0), "book": (0.0, 90.0, 0.0), "duck": (0.0, 90.0, 30.0)}
"""Per suite object, the `placement_deg` of a second placement that shows the first one's underside: on its side,
or upside down for the flat ones (others: on its side, 90 degrees about X)."""


@dataclass
class GroundTruth:
    """Where the simulated object stands in a session's turntable frame."""

    model_dir: Path
    """The object's model directory (mesh.obj, models_info.json)."""
    T_turntable_obj: np.ndarray
    """4x4 pose of the model frame in the turntable frame, metres (the first placement's)."""
    placements: list[np.ndarray] = field(default_factory=list)
    """4x4 pose of the model frame in each placement's turntable frame (the first is T_turntable_obj)."""

    def T_first_placement(self, index: int) -> np.ndarray:
        """4x4 pose of placement `index`'s turntable frame in the first placement's: what registration finds."""
        return self.placements[0] @ inv_T(self.placements[index])

    def underside(self, fraction: float = 0.1) -> np.ndarray:
        """The model's vertices (first placement's turntable frame) within `fraction` of its height of the plate:
        the part a one-placement capture never sees."""
        points = transform_points(self.T_turntable_obj, model_vertices(self.model_dir))
        return points[points[:, 2] <= fraction * points[:, 2].max()]


def ground_truth(world: SimWorldConfig, placements: Sequence[SimWorldConfig] = ()) -> GroundTruth:
    """The object of `world` as it stands on the plate at plate angle 0 (the session's turntable frame), and its
    pose in each further placement."""
    T = T_plate_obj(world)
    return GroundTruth(object_dir(world), T, [T] + [T_plate_obj(w) for w in placements])


def turned(world: SimWorldConfig, placement_deg: tuple[float, float, float] | None = None) -> SimWorldConfig:
    """`world` with the object turned over: `placement_deg`, or the object's `SECOND_PLACEMENT_DEG`."""
    name = Path(world.object).name
    return replace(world, placement_deg=placement_deg or SECOND_PLACEMENT_DEG.get(name, (90.0, 0.0, 0.0)))


def render_session(out: str | Path, world: SimWorldConfig, views: int, *, noise: bool = True, seed: int = 0,
                   overwrite: bool = False, progress: ProgressFn = no_progress,
                   placements: Sequence[SimWorldConfig] = ()) -> GroundTruth:
    """Render `views` plate angles evenly over a turn into the capture session `out`; returns the truth.

    `placements`: the worlds of further placements (the object turned over, `turned(world)`), each swept with
    `views` more views in its own turntable frame (transforms.json frames marked with their placement index)."""
    angles = np.arange(views) * 2 * math.pi / views
    rng = np.random.default_rng(seed)
    worlds = [world, *placements]
    total = views * len(worlds)
    with stage_output(out, "capture_session", overwrite=overwrite, resume=False, config=None) as writer:
        frames, records = [], []
        for p, placed in enumerate(worlds):
            with SimCamera(placed) as camera:
                for angle in angles:
                    i = len(frames)
                    frame = camera.render(float(angle))
                    image, mask = f"images/{i:04d}.png", f"masks/{i:04d}.png"
                    write_png(writer.path / image, camera.noisy(frame.rgb, rng) if noise else frame.rgb)
                    if noise:
                        write_png(writer.path / TRUTH_DIR / image, frame.rgb)
                    write_png(writer.path / mask, frame.mask.astype(np.uint8) * 255)
                    frames.append((image, mask, inv_T(frame.T_cam_turntable @ rot_z(float(angle)))))
                    records.append({"index": i, "file": image, "mask": mask, "angle_rad": float(angle)}
                                   | ({"placement": p} if placements else {}))
                    progress(Progress((i + 1) / total, "rendering", message=f"view {i + 1}/{total}"))
        atomic_write_json(writer.path / "transforms.json",
                          transforms_json(sim_world.K(world), None, world.width, world.height, frames,
                                          [r.get("placement", 0) for r in records]))
        capture = {"board": world.board.to_dict(), "pose_source": "simulator ground truth",
                   "render": {"samples": world.samples, "denoiser": world.denoiser}, "views": records}
        if placements:
            capture["placements"] = [{"index": p, "views": views, "simulated_placement_deg": list(w.placement_deg)}
                                     for p, w in enumerate(worlds)]
        atomic_write_json(writer.path / "capture.json", capture)
        writer.finish(extra={"views": total, "simulated": True} | ({"placements": len(worlds)} if placements else {}))
    return ground_truth(world, placements)


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
    parser.add_argument("--placements", type=int, default=1, choices=(1, 2),
                        help="2: sweep, turn the object over (SECOND_PLACEMENT_DEG), sweep again")
    parser.add_argument("--clutter-seed", type=int, default=0, help="another seed: another scene around the plate")
    parser.add_argument("--seed", type=int, default=0, help="seed of the camera noise")
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args(argv)
    if args.views < 1:
        parser.error("--views must be >= 1")
    try:
        world = SimWorldConfig(object=args.object, width=args.width, height=args.height,
                               focal_px=SimWorldConfig().focal_px * args.width / 640, samples=args.samples,
                               clutter_seed=args.clutter_seed)
    except ValueError as exc:
        parser.error(str(exc))
    render_session(args.out, world, args.views, seed=args.seed, overwrite=args.overwrite,
                   placements=[turned(world)] if args.placements == 2 else ())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
