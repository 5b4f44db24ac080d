"""Benchmark of the dataset stage: annotated vs bare throughput at 640x480, annotation accuracy, memory.

    python benchmarks/dataset.py [--frames 20] [--models box,bottle] [--workers 1] [--out DIR]

Renders `--frames` frames of the sample objects with the default config (annotated: label render,
masks, depth, BOP + DOPE files), then the same frames (same seed: same scenes) bare, without any
annotation pass, in the same run, and prints frames/hour of both and the annotation overhead (goal
<= 15 %). Then measures the annotated dataset with `n2d_dataset.check` (mask boundary against the
projected meshes, depth against the meshes, visib_fract against a recount) and the render worker's
memory over the frames (resident MiB at the first and last frame: the scene reset must keep it flat).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from pathlib import Path

from n2d_common.config import load_config
from n2d_dataset.check import check_dataset
from n2d_dataset.config import DatasetConfig
from n2d_dataset.generate import generate_dataset
from n2d_sim.objects import sample_object_dir
from table import print_table

OVERHEAD_GOAL_PCT = 15.0


def _run(models, out: Path, cfg: DatasetConfig) -> float:
    t0 = time.perf_counter()
    generate_dataset(models, out, cfg)
    return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--models", default="box,bottle", help="sample objects or model directories, comma-separated")
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--out", type=Path, help="keep the datasets here (default: a temporary directory)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="dataset config override")
    args = parser.parse_args()
    models = [Path(m) if os.sep in m else sample_object_dir(m) for m in args.models.split(",")]
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp)
        cfg = load_config(DatasetConfig, overrides=args.set + [f"frames={args.frames}", f"workers={args.workers}"])
        annotated_s = _run(models, out / "annotated", cfg)
        cfg.annotate = False
        bare_s = _run(models, out / "bare", cfg)
        manifest = json.loads((out / "annotated" / "n2d.json").read_text())["extra"]
        check = check_dataset(out / "annotated")
    n = args.frames
    overhead = 100.0 * (annotated_s - bare_s) / bare_s
    machine = f"{platform.processor() or platform.machine()}, {len(os.sched_getaffinity(0))} cores"
    phases, rss = manifest["phase_seconds"], manifest["worker_rss_mb"]
    rows = [
        ("annotated frames/hour", f"{3600 * n / annotated_s:.0f}", "", f"{annotated_s / n:.2f} s/frame"),
        ("bare frames/hour (same scenes)", f"{3600 * n / bare_s:.0f}", "", f"{bare_s / n:.2f} s/frame"),
        ("annotation overhead", f"{overhead:.1f} %", f"<= {OVERHEAD_GOAL_PCT:g} %",
         "met" if overhead <= OVERHEAD_GOAL_PCT else "NOT met"),
        ("per-frame phases (annotated)", ", ".join(f"{k} {v / n:.2f} s" for k, v in phases.items()), "", ""),
        ("render worker memory", f"{rss['first_frame']:.0f} -> {rss['last_frame']:.0f} MiB", "flat",
         f"first -> last frame, max {rss['max']:.0f} MiB"),
        ("instances annotated", str(check["instances"]), "", f"{check['fully_visible_instances']} fully visible"),
        ("mask boundary vs projected mesh", f"{check['mask_boundary_offset_px']['mean']:.3f} px mean",
         "<= 0.5 px", f"max {check['mask_boundary_offset_px']['max']:.3f} px"),
        ("depth vs mesh under the pose", f"{check['depth_error_mm']['mean']:.3f} mm mean", "<= 1 mm",
         f"p95 {check['depth_error_mm']['p95']:.3f} mm"),
        ("visib_fract vs recount", f"{check['visib_fract_error']['mean']:.4f} mean", "",
         f"max {check['visib_fract_error']['max']:.4f}"),
        ("DOPE cuboid vs BOP pose", f"{check['dope_vs_pose_px_max']:.2e} px max", "", ""),
    ]
    c, r = cfg.camera, cfg.render
    print_table(f"dataset: {n} frames {c.width}x{c.height}, {r.samples} spp + {r.denoiser}, {args.workers} worker(s), "
                f"{machine}", rows, ("metric", "value", "goal", "note"))


if __name__ == "__main__":
    main()
