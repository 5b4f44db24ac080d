"""Benchmark of refinement and tracking: a DOPE model on validation videos of the simulator, three ways.

    python benchmarks/tracking.py --model DOPE_DIR [--object-model MODEL_DIR] [--frames 90] [--scenes tabletop,in_hand]
                                  [--seed 0] [--out DIR]

Each scene (`n2d_dataset.sequence`: tabletop, the camera circling the object among distractors at 30 deg/s; in
hand, the object turning at 90 deg/s in a gripper, underside included) is rendered once (640 x 480, 30 FPS) and
run through: DOPE alone on every frame; DOPE with region-based refinement on every frame; and the tracker
(`n2d_dope.track`: refinement from the last pose, DOPE again every 10 frames or when lost). Printed per scene and
way: ADD-S and ADD accuracy at 10 % of the diameter over the frames where at least 25 % of the object is visible
(a frame without a pose counts as a miss), median rotation and translation error, lost frames (no pose), jitter
(median frame-to-frame change of the pose error: millimetres / degrees), and milliseconds per frame (the tracker:
tracked frames and detected frames apart). A contact sheet per scene (`tracking_<scene>.png` in `--out`, the DOPE
directory by default) shows the truth (white) and the tracker's pose (green) on evenly spread frames.
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path

import numpy as np

from n2d_common.frames import project
from n2d_common.images import contact_sheet, draw_cuboid, write_png
from n2d_dataset.sequence import Sequence, SequenceConfig
from n2d_dope.config import RefineConfig
from n2d_dope.evaluate import model_points
from n2d_dope.infer import DopeModel
from n2d_dope.metrics import add, add_s
from n2d_dope.track import Tracker
from table import print_table

SPEEDS = {"tabletop": 30.0, "in_hand": 90.0}
"""Angular speed per scene, deg/s."""
MIN_VISIBLE = 0.25
ADDS_GOAL = 0.9
"""Tracker: share of frames within 10 % of the diameter (ADD-S)."""
JITTER_GOAL = (0.5, 0.2)
"""Tracker: median frame-to-frame change of the pose error, mm and deg."""


def _errors(T_est: np.ndarray | None, T_gt: np.ndarray, points: np.ndarray) -> tuple[float, ...]:
    """(ADD, ADD-S, rotation deg, translation mm); inf without a pose."""
    if T_est is None:
        return (np.inf,) * 4
    R = T_est[:3, :3].T @ T_gt[:3, :3]
    rot = float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))
    return add(T_est, T_gt, points), add_s(T_est, T_gt, points), rot, 1000 * float(np.linalg.norm(T_est[:3, 3] -
                                                                                                    T_gt[:3, 3]))


def _jitter(poses: list[np.ndarray | None], truths: list[np.ndarray]) -> tuple[float, float]:
    """Median frame-to-frame change of the pose error in the object frame (T_gt^-1 T_est: mm at the object's
    origin, deg) over consecutive frames that both have a pose."""
    dt, dr = [], []
    for a, b, ga, gb in zip(poses, poses[1:], truths, truths[1:]):
        if a is None or b is None:
            continue
        ea, eb = np.linalg.inv(ga) @ a, np.linalg.inv(gb) @ b
        change = np.linalg.inv(ea) @ eb
        dt.append(1000 * np.linalg.norm(change[:3, 3]))
        dr.append(np.degrees(np.arccos(np.clip((np.trace(change[:3, :3]) - 1) / 2, -1, 1))))
    return (float(np.median(dt)), float(np.median(dr))) if dt else (float("nan"), float("nan"))


def summarise(name: str, poses: list, truths: list, visible: list, points: np.ndarray, diameter: float) -> dict:
    errors = np.array([_errors(T, G, points) for T, G in zip(poses, truths)])
    scored = np.array(visible) >= MIN_VISIBLE
    e = errors[scored]
    found = np.isfinite(e[:, 0])
    jitter = _jitter(poses, truths)
    return {"way": name, "frames": int(scored.sum()), "adds": float(np.mean(e[:, 1] < 0.1 * diameter)),
            "add": float(np.mean(e[:, 0] < 0.1 * diameter)),
            "rot_deg": float(np.median(e[found, 2])) if found.any() else float("nan"),
            "trans_mm": float(np.median(e[found, 3])) if found.any() else float("nan"),
            "lost": int((~found).sum()), "jitter_mm": jitter[0], "jitter_deg": jitter[1]}


def run_scene(scene: str, args, plain: DopeModel, refined: DopeModel, points: np.ndarray, diameter: float,
              out: Path) -> list[dict]:
    seq = Sequence(args.object_model, SequenceConfig(scene=scene, frames=args.frames, speed_deg_s=SPEEDS[scene],
                                                     seed=args.seed))
    t0 = time.perf_counter()
    frames = [seq.frame(i) for i in range(len(seq))]
    print(f"{scene}: {len(frames)} frames rendered in {time.perf_counter() - t0:.0f} s "
          f"(visible {np.mean([f.visible for f in frames]):.2f} on average)", flush=True)
    truths, visible, K = [f.T_cam_obj for f in frames], [f.visible for f in frames], seq.K
    results = []
    for name, model in (("DOPE", plain), ("DOPE + refinement", refined)):
        poses, ms = [], []
        for f in frames:
            t = time.perf_counter()
            found = model.detect(f.rgb, K)
            ms.append(1000 * (time.perf_counter() - t))
            best = max(found, key=lambda d: d.score, default=None)
            poses.append(None if best is None else best.T_cam_obj)
        results.append({**summarise(name, poses, truths, visible, points, diameter), "ms": float(np.mean(ms))})

    tracker = Tracker(refined)
    poses, track_ms, detect_ms, sheet, labels = [], [], [], [], []
    pick = set(np.linspace(0, len(frames) - 1, 8).round().astype(int).tolist())
    for i, f in enumerate(frames):
        t = time.perf_counter()
        detecting = tracker.needs_detection()
        pose = tracker.step(f.rgb, K, f.stamp)
        (detect_ms if detecting else track_ms).append(1000 * (time.perf_counter() - t))
        poses.append(None if pose is None else pose.T_cam_obj)
        if i in pick:
            img = f.rgb.copy()
            draw_cuboid(img, project(K, f.T_cam_obj, refined.cuboid_m)[:8], (255, 255, 255), (255, 255, 255))
            if pose is not None:
                draw_cuboid(img, project(K, pose.T_cam_obj, refined.cuboid_m)[:8], (0, 255, 0), (0, 160, 0), 2)
            sheet.append(img)
            labels.append(f"{f.stamp:.2f} s " + ("lost" if pose is None else pose.source))
    row = summarise("tracker", poses, truths, visible, points, diameter)
    row["ms"] = float(np.mean(track_ms)) if track_ms else float("nan")
    row["detect_ms"] = float(np.mean(detect_ms)) if detect_ms else float("nan")
    row["detections"] = len(detect_ms)
    results.append(row)
    write_png(out / f"tracking_{scene}.png", contact_sheet(sheet, labels))
    return results


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--model", type=Path, required=True, help="DOPE model directory")
    p.add_argument("--object-model", type=Path, help="the object's model directory (default: the one DOPE was "
                   "trained on)")
    p.add_argument("--frames", type=int, default=90)
    p.add_argument("--scenes", default="tabletop,in_hand")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, help="where the contact sheets go (default: the DOPE directory)")
    args = p.parse_args()
    plain = DopeModel(args.model)
    args.object_model = plain.object_dir(args.object_model)
    refined = DopeModel(args.model, refine=RefineConfig(), object_dir=args.object_model)
    points, diameter = model_points(args.object_model)
    out = args.out or args.model
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for scene in args.scenes.split(","):
        for r in run_scene(scene, args, plain, refined, points, diameter, out):
            tracker = r["way"] == "tracker"
            met = ("met" if r["adds"] >= ADDS_GOAL else "NOT met") if tracker else ""
            rate = (f"{r['ms']:.1f} ms a tracked frame ({1000 / r['ms']:.0f} FPS), detection frames "
                    f"{r['detect_ms']:.0f} ms ({r['detections']} of them)" if tracker else f"{r['ms']:.0f} ms a frame")
            accuracy = f"{100 * r['adds']:.1f} % / {100 * r['add']:.1f} %"
            rows.append((f"{scene}: {r['way']}: ADD-S / ADD at 10 %", accuracy,
                         f">= {100 * ADDS_GOAL:.0f} % ADD-S" if tracker else "", met,
                         f"median {r['rot_deg']:.2f} deg / {r['trans_mm']:.1f} mm; lost {r['lost']} of "
                         f"{r['frames']} frames; {rate}"))
            if tracker:
                jitter_met = r["jitter_mm"] <= JITTER_GOAL[0] and r["jitter_deg"] <= JITTER_GOAL[1]
                rows.append((f"{scene}: tracker: jitter (frame-to-frame change of the error)",
                             f"{r['jitter_mm']:.2f} mm / {r['jitter_deg']:.2f} deg",
                             f"<= {JITTER_GOAL[0]} mm / {JITTER_GOAL[1]} deg", "met" if jitter_met else "NOT met",
                             "median over consecutive frames that both have a pose"))
    machine = f"{platform.processor() or platform.machine()}, {len(__import__('os').sched_getaffinity(0))} cores"
    print_table(f"tracking: {args.model.name} on {args.object_model.name}, {args.frames} frames per scene at "
                f"640 x 480; {machine}", rows, ("metric", "value", "goal", "met", "note"))


if __name__ == "__main__":
    main()
