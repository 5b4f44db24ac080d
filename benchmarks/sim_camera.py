"""Benchmark of the simulated camera: new-angle render latency and republish-with-noise rate.

    python benchmarks/sim_camera.py [--angles 10] [--set samples=4 --set denoiser=none] [--sheet /tmp/sim.png]
                                    [--reference-samples 256]

Prints the settings, the worker start time, the render latency over new plate angles (after one
warm-up render) and the rate at which the last frame can be republished with fresh sensor noise.
`--sheet` also writes a contact sheet of the rendered frames with the object mask outlined.
`--reference-samples N` renders the same angles again at N samples per pixel and prints how far the
frames are from them (PSNR / SSIM over the object mask): Monte-Carlo noise and denoiser artefacts change
from view to view, so this is the best any 3-D model of the object can score against these frames.
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from n2d_common.config import apply_overrides, from_dict, to_dict
from n2d_common.images import contact_sheet, draw_mask_outline, write_png
from n2d_reconstruct.metrics import psnr, ssim
from n2d_sim.camera import SimCamera
from n2d_sim.world import SimWorldConfig
from table import print_table


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--angles", type=int, default=10, help="new plate angles to time after the warm-up")
    parser.add_argument("--republish", type=int, default=50, help="noisy republished frames to time")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="SimWorldConfig override, e.g. samples=4 (repeatable)")
    parser.add_argument("--sheet", type=Path, help="write a contact sheet of the frames (PNG)")
    parser.add_argument("--reference-samples", type=int, default=0,
                        help="also compare the frames with renders at this many samples per pixel")
    args = parser.parse_args(argv)
    if args.reference_samples < 0:
        parser.error("--reference-samples must be >= 1 (0: no comparison)")
    cfg = from_dict(SimWorldConfig, apply_overrides(to_dict(SimWorldConfig()), args.overrides))

    t0 = time.perf_counter()
    with SimCamera(cfg) as cam:
        start_s = time.perf_counter() - t0
        cam.render(0.0)
        frames, latencies = [], []
        for i in range(args.angles):
            frame = cam.render(2 * math.pi * (i + 0.5) / args.angles)
            frames.append(frame)
            latencies.append(frame.render_s)
        rng = np.random.default_rng(0)
        t0 = time.perf_counter()
        for _ in range(args.republish):
            cam.noisy(frames[-1].rgb, rng)
        noise_s = (time.perf_counter() - t0) / args.republish
        device = cam.info.get("device", "?")

    mean, median = statistics.mean(latencies), statistics.median(latencies)
    rows = [
        ("resolution", f"{cfg.width}x{cfg.height}"),
        ("object", cfg.object),
        ("device", f"{device}, threads {cfg.threads or 'all'}"),
        ("samples / denoiser", f"{cfg.samples} / {cfg.denoiser}"),
        ("background samples", f"{cfg.background_samples} (rendered once)"),
        ("light bounces", str(cfg.max_bounces)),
        ("clutter", str(cfg.clutter)),
        ("worker start (import, build, background)", f"{start_s:.1f} s"),
        (f"new-angle render, mean / median of {len(latencies)}", f"{mean:.2f} s / {median:.2f} s"),
        ("new-angle rate", f"{1 / mean:.2f} frames/s"),
        ("republish with noise", f"{noise_s * 1000:.1f} ms -> {1 / noise_s:.0f} frames/s"),
    ]
    if args.reference_samples:
        rows += _consistency(cfg, frames, args.reference_samples)
    print_table("simulated camera benchmark", rows)

    if args.sheet:
        images = [draw_mask_outline(f.rgb, f.mask, (0, 255, 0)) for f in frames]
        labels = [f"{math.degrees(f.angle_rad):.0f} deg, {f.render_s:.2f} s" for f in frames]
        write_png(args.sheet, contact_sheet(images, labels, cols=min(4, len(images))))
        print(f"  contact sheet: {args.sheet}")


def _consistency(cfg: SimWorldConfig, frames: list, samples: int) -> list[tuple[str, str]]:
    """Rows: PSNR / SSIM (object mask) of `frames` against renders of the same angles at `samples` spp."""
    with SimCamera(replace(cfg, samples=samples)) as cam:
        references = [cam.render(f.angle_rad) for f in frames]
    db = [psnr(r.rgb, f.rgb, r.mask) for f, r in zip(frames, references)]
    sim = [ssim(r.rgb, f.rgb, r.mask) for f, r in zip(frames, references)]
    return [(f"vs {samples}-sample renders (object mask): PSNR mean / min",
             f"{statistics.mean(db):.2f} / {min(db):.2f} dB"),
            ("  SSIM mean / min", f"{statistics.mean(sim):.4f} / {min(sim):.4f}")]


if __name__ == "__main__":
    main()
