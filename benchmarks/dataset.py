"""Benchmark of the dataset stage: annotated frames per CPU-hour of both renderers at 640x480, the Cycles path's
annotation overhead, annotation accuracy of both, memory.

    python benchmarks/dataset.py [--frames 20] [--raster-frames 200] [--models box,bottle] [--workers 0] [--out DIR]
    python benchmarks/dataset.py --cluster local --workers 1,2 [--raster-frames 200]

Renders `--frames` frames of the sample objects with the photoreal Cycles path (the default config: 16 spp +
OIDN) and `--raster-frames` with the fast rasterizer (`render.engine=raster`), both annotated (labels, masks,
depth, BOP + DOPE files), and prints frames/hour of each and their ratio (goal: the fast path >= 10x). The
Cycles frames are rendered again bare (same seed: same scenes) to print the annotation overhead (goal <= 15 %).
Both datasets are measured with `n2d_dataset.check` (mask boundary against the projected meshes, goal <= 0.5
px; depth against the meshes; visib_fract against a recount) and the render workers' memory over the frames
(resident MiB at the first and last frame: it must stay flat). Wall times include the workers' start.

With `--cluster ADDRESS` (`local`: a Ray cluster of this machine) it measures the Ray path instead: for each
worker count of `--workers` the `--raster-frames` fast-path frames rendered by plain local workers and by Ray
actors on the cluster (the same frames, checked file for file), frames/hour of both and the overhead per frame
(goal at 1 worker: <= 5 %). From the measured per-frame cost, the bytes a frame sends back and the driver's
time to write one, a model (not a measurement) predicts frames/hour at 8 and 32 workers: K workers render
K / (cost + overhead) frames a second, capped by the driver writing them one after another and by the head's
link (`--link-mbps`, 1000 by default) carrying their bytes.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from n2d_common.config import load_config
from n2d_dataset.check import check_dataset
from n2d_dataset.cluster import WRITE_THREADS, write_frame_files
from n2d_dataset.config import DatasetConfig
from n2d_dataset.generate import generate_dataset
from n2d_sim.objects import sample_object_dir
from table import print_table

OVERHEAD_GOAL_PCT = 15.0
CLUSTER_OVERHEAD_GOAL_PCT = 5.0


SPEEDUP_GOAL = 10.0


def _run(models, out: Path, cfg: DatasetConfig) -> float:
    t0 = time.perf_counter()
    generate_dataset(models, out, cfg)
    return time.perf_counter() - t0


def _rows(name: str, n: int, seconds: float, out: Path) -> list[tuple]:
    manifest = json.loads((out / "n2d.json").read_text())["extra"]
    check = check_dataset(out)
    phases, rss = manifest["phase_seconds"], manifest["worker_rss_mb"]
    return [
        (f"{name}: annotated frames/hour", f"{3600 * n / seconds:.0f}", "", f"{seconds / n:.2f} s/frame"),
        (f"{name}: per-frame phases (annotated, per worker)",
         ", ".join(f"{k} {v / n:.2f} s" for k, v in phases.items()), "", ""),
        (f"{name}: render worker memory", f"{rss['first_frame']:.0f} -> {rss['last_frame']:.0f} MiB", "flat",
         f"first -> last frame, max {rss['max']:.0f} MiB"),
        (f"{name}: instances annotated", str(check["instances"]), "",
         f"{check['fully_visible_instances']} fully visible"),
        (f"{name}: mask boundary vs projected mesh", f"{check['mask_boundary_offset_px']['mean']:.3f} px mean",
         "<= 0.5 px", f"max {check['mask_boundary_offset_px']['max']:.3f} px"),
        (f"{name}: depth vs mesh under the pose", f"{check['depth_error_mm']['mean']:.3f} mm mean", "<= 1 mm",
         f"p95 {check['depth_error_mm']['p95']:.3f} mm"),
        (f"{name}: visib_fract vs recount", f"{check['visib_fract_error']['mean']:.4f} mean", "",
         f"max {check['visib_fract_error']['max']:.4f}"),
        (f"{name}: DOPE cuboid vs BOP pose", f"{check['dope_vs_pose_px_max']:.2e} px max", "", ""),
    ]


def _hashes(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file() and p.name != "n2d.json"}


def _driver_write_s(dataset: Path, scratch: Path) -> float:
    """Seconds per frame the driver takes to write the frames as they come back (atomic writes with fsync, in
    its WRITE_THREADS writer threads), replayed from a finished dataset."""
    frames: dict[str, list] = {}
    for p in sorted((dataset / "train_pbr").rglob("*")):
        if p.is_file() and p.parent.name in ("rgb", "depth", "mask", "mask_visib") and not p.name.startswith("_"):
            frames.setdefault(f"{p.parent.parent.name}/{p.name[:6]}", []).append(
                (str(p.relative_to(dataset)), p.read_bytes()))
    t0 = time.perf_counter()
    with ThreadPoolExecutor(WRITE_THREADS) as pool:
        list(pool.map(lambda files: write_frame_files(scratch, files), frames.values()))
    return (time.perf_counter() - t0) / len(frames)


def cluster_main(args, models) -> None:
    from n2d_common.cluster import connect, nodes

    counts = [int(k) for k in args.workers.split(",")]
    n, rows = args.raster_frames, []
    model = {}
    with tempfile.TemporaryDirectory() as tmp, connect(args.cluster) as ray:
        out = args.out or Path(tmp)
        slots = int(sum(node.cpus for node in nodes(ray)))
        for k in counts:
            # one thread per worker on both paths (what a Ray slot of one CPU gets), so only the executor differs
            cfg = load_config(DatasetConfig, overrides=[f"frames={n}", f"workers={k}", "render.engine=raster",
                                                        "render.threads=1"] + args.set)
            plain_s = _run(models, out / f"plain_{k}", cfg)
            t0 = time.perf_counter()
            generate_dataset(models, out / f"ray_{k}", cfg, cluster=args.cluster)
            ray_s = time.perf_counter() - t0
            same = _hashes(out / f"plain_{k}") == _hashes(out / f"ray_{k}")
            overhead = 100.0 * (ray_s - plain_s) / plain_s
            rows += [(f"{k} worker(s): plain frames/hour", f"{3600 * n / plain_s:.0f}", "",
                      f"{plain_s / n:.3f} s/frame"),
                     (f"{k} worker(s): Ray frames/hour", f"{3600 * n / ray_s:.0f}", "",
                      f"{ray_s / n:.3f} s/frame; files identical: {'yes' if same else 'NO'}"),
                     (f"{k} worker(s): Ray overhead per frame", f"{overhead:.1f} %",
                      f"<= {CLUSTER_OVERHEAD_GOAL_PCT:g} %" if k == 1 else "",
                      f"{1000 * (ray_s - plain_s) / n:.1f} ms/frame" + (
                          (" met" if overhead <= CLUSTER_OVERHEAD_GOAL_PCT else " NOT met") if k == 1 else ""))]
            if k == counts[0]:
                size = sum(p.stat().st_size for p in (out / f"plain_{k}" / "train_pbr").rglob("*") if p.is_file())
                model = {"cost": plain_s * k / n, "overhead": max(0.0, (ray_s - plain_s) * k / n),
                         "bytes": size / n, "write": _driver_write_s(out / f"plain_{k}", out / "replay")}
    link = args.link_mbps * 1e6 / 8
    rows.append(("model inputs", f"{model['cost']:.3f} s/frame per worker + {1000 * model['overhead']:.1f} ms Ray",
                 "", f"{model['bytes'] / 1024:.0f} KiB back per frame, the driver writes one per "
                     f"{1000 * model['write']:.1f} ms ({WRITE_THREADS} threads), head link {args.link_mbps:g} Mbit/s"))
    for k in (8, 32):
        rate = min(k / (model["cost"] + model["overhead"]), 1 / model["write"], link / model["bytes"])
        limit = ("workers" if rate == k / (model["cost"] + model["overhead"]) else
                 "driver writes" if rate == 1 / model["write"] else "head link")
        rows.append((f"{k} workers: frames/hour (model, not measured)", f"{3600 * rate:.0f}", "",
                     f"limited by the {limit}"))
    machine = f"{platform.processor() or platform.machine()}, {len(os.sched_getaffinity(0))} cores"
    c = cfg.camera
    print_table(f"dataset on Ray ({args.cluster}, {slots} CPU slots): raster {n} frames at {c.width}x{c.height}; "
                f"{machine}", rows, ("metric", "value", "goal", "note"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=20, help="Cycles frames")
    parser.add_argument("--raster-frames", type=int, default=200, help="fast-path frames")
    parser.add_argument("--models", default="box,bottle", help="sample objects or model directories, comma-separated")
    parser.add_argument("--workers", default="0", help="render workers (0: automatic for each path); with "
                        "--cluster, a comma-separated list of worker counts to measure")
    parser.add_argument("--cluster", help="measure the Ray path on this cluster (local: one of this machine)")
    parser.add_argument("--link-mbps", type=float, default=1000.0, help="the head's network link in the scaling "
                        "model, Mbit/s")
    parser.add_argument("--out", type=Path, help="keep the datasets here (default: a temporary directory)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="dataset config override")
    args = parser.parse_args()
    models = [Path(m) if os.sep in m else sample_object_dir(m) for m in args.models.split(",")]
    if args.cluster:
        cluster_main(args, models)
        return
    n, nr = args.frames, args.raster_frames
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp)
        cfg = load_config(DatasetConfig, overrides=args.set + [f"frames={n}", f"workers={args.workers}"])
        fast = load_config(DatasetConfig, overrides=args.set + [f"frames={nr}", f"workers={args.workers}",
                                                                "render.engine=raster"])
        raster_s = _run(models, out / "raster", fast)
        annotated_s = _run(models, out / "annotated", cfg)
        cfg.annotate = False
        bare_s = _run(models, out / "bare", cfg)
        rows = _rows("cycles", n, annotated_s, out / "annotated") + _rows("raster", nr, raster_s, out / "raster")
    overhead = 100.0 * (annotated_s - bare_s) / bare_s
    speedup = (nr / raster_s) / (n / annotated_s)
    machine = f"{platform.processor() or platform.machine()}, {len(os.sched_getaffinity(0))} cores"
    rows[1:1] = [("cycles: bare frames/hour (same scenes)", f"{3600 * n / bare_s:.0f}", "",
                  f"{bare_s / n:.2f} s/frame"),
                 ("cycles: annotation overhead", f"{overhead:.1f} %", f"<= {OVERHEAD_GOAL_PCT:g} %",
                  "met" if overhead <= OVERHEAD_GOAL_PCT else "NOT met")]
    rows.append(("fast path vs Cycles, annotated frames per CPU-hour", f"{speedup:.1f}x", f">= {SPEEDUP_GOAL:g}x",
                 "met" if speedup >= SPEEDUP_GOAL else "NOT met"))
    c, r = cfg.camera, cfg.render
    print_table(f"dataset: {c.width}x{c.height}; cycles {n} frames, {r.samples} spp + {r.denoiser}, "
                f"{cfg.worker_count()} worker(s); raster {nr} frames, {fast.worker_count()} worker(s); {machine}",
                rows, ("metric", "value", "goal", "note"))


if __name__ == "__main__":
    main()
