"""Benchmark of the foreground masks on the simulated turntable: IoU against the exact mask, and speed.

    python benchmarks/masks.py [--angles 12] [--size 640x480] [--set close_px=6] [--sheet /tmp/masks.png]

For each sample object, renders the view and the empty plate at `--angles` plate angles, adds
independent sensor noise to both, and runs each variant: with the reference (and the plate
geometry), and without it. Prints mean and min IoU and the milliseconds per frame, and writes a
contact sheet of crops around the object (and the computed mask): the exact outline in blue, the computed one in green
(with the reference) or red (without).
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from functools import partial
from pathlib import Path

import cv2
import numpy as np

from n2d_capture.masks import MaskConfig, ViewGeometry, foreground_mask, foreground_mask_no_reference, iou
from n2d_common.config import apply_overrides, from_dict, to_dict
from n2d_common.images import contact_sheet, draw_mask_outline, write_png
from n2d_sim.camera import SimCamera
from n2d_sim.objects import SAMPLE_OBJECTS
from n2d_sim.world import SimWorldConfig
from table import print_table

VARIANTS = {"reference": (0, 255, 0), "no reference": (255, 0, 0)}
"""Variant name: outline colour on the sheet."""
EXACT_COLOUR = (0, 128, 255)


def _crop(image: np.ndarray, masks: list[np.ndarray], size: tuple[int, int] = (400, 300)) -> np.ndarray:
    """The part of `image` around all `masks` (a margin added, widened to the aspect of `size`), resized
    to `size` (width, height)."""
    h, w = image.shape[:2]
    ys, xs = np.nonzero(np.logical_or.reduce(masks))
    cy, cx = (ys.min() + ys.max()) / 2, (xs.min() + xs.max()) / 2
    ch = max(ys.max() - ys.min(), (xs.max() - xs.min()) * size[1] / size[0]) * 1.3 + 16
    ch = min(ch, h, w * size[1] / size[0])
    cw = ch * size[0] / size[1]
    y0 = round(np.clip(cy - ch / 2, 0, h - ch))
    x0 = round(np.clip(cx - cw / 2, 0, w - cw))
    return cv2.resize(image[y0:y0 + round(ch), x0:x0 + round(cw)], size, interpolation=cv2.INTER_AREA)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--angles", type=int, default=12, help="plate angles per sample object")
    parser.add_argument("--size", default="640x480", help="image size WxH (the focal length scales with W)")
    parser.add_argument("--objects", nargs="+", default=list(SAMPLE_OBJECTS), choices=SAMPLE_OBJECTS)
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="MaskConfig override, e.g. close_px=6 (repeatable)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the sensor noise")
    parser.add_argument("--sheet", type=Path, default=Path("/tmp/n2d_masks.png"),
                        help="where to write the contact sheet (PNG)")
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.size.lower().split("x"))
    cfg = from_dict(MaskConfig, apply_overrides(to_dict(MaskConfig()), args.overrides))
    rng = np.random.default_rng(args.seed)

    rows, tiles, labels = [], [], []
    for name in args.objects:
        world = SimWorldConfig(object=name, width=width, height=height,
                               focal_px=SimWorldConfig.focal_px * width / SimWorldConfig.width)
        scores: dict[str, list[float]] = {v: [] for v in VARIANTS}
        times: dict[str, list[float]] = {v: [] for v in VARIANTS}
        with SimCamera(world) as cam:
            for i in range(args.angles):
                angle = 2 * math.pi * (i + 0.5) / args.angles
                frame = cam.render(angle)
                rgb = cam.noisy(frame.rgb, rng)
                reference = cam.noisy(cam.render(angle, object_visible=False).rgb, rng)
                geometry = ViewGeometry.from_turntable(frame.K, frame.T_cam_turntable, angle, world.board)
                runs = {"reference": partial(foreground_mask, rgb, reference, geometry, cfg),
                        "no reference": partial(foreground_mask_no_reference, rgb, geometry, cfg)}
                for variant, run in runs.items():
                    t0 = time.perf_counter()
                    mask = run()
                    times[variant].append(time.perf_counter() - t0)
                    scores[variant].append(iou(mask, frame.mask))
                    image = draw_mask_outline(rgb, frame.mask, EXACT_COLOUR)
                    image = draw_mask_outline(image, mask, VARIANTS[variant])
                    tiles.append(_crop(image, [frame.mask, mask]))
                    labels.append(f"{name} {math.degrees(angle):.0f} deg, {variant}: {scores[variant][-1]:.3f}")
        for variant in VARIANTS:
            rows.append((name, variant, statistics.mean(scores[variant]), min(scores[variant]),
                         1000 * statistics.mean(times[variant])))

    print_table(f"foreground masks, {width}x{height}, {args.angles} angles per object, noise on view and reference",
                [(name, variant, f"{mean:.4f}", f"{low:.4f}", f"{ms:.0f}") for name, variant, mean, low, ms in rows],
                ("object", "variant", "mean IoU", "min IoU", "ms/frame"))
    write_png(args.sheet, contact_sheet(tiles, labels, cols=4, thumb_width=tiles[0].shape[1]))
    print(f"  contact sheet: {args.sheet}")


if __name__ == "__main__":
    main()
