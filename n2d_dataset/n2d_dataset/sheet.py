"""The dataset's contact sheet: random frames with visible-mask outlines, projected cuboids and object axes
drawn from the written annotations (the DOPE JSON for cuboids, BOP scene_gt + K for axes), so a person
sees at a glance that the labels sit on the objects and that both formats agree.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from n2d_common.frames import make_T
from n2d_common.images import contact_sheet, draw_axes, draw_cuboid, draw_mask_outline, read_png, write_png
from n2d_dataset.writer import frame_location, rgb_name


def draw_frame(rgb: np.ndarray, dope: dict, gt: list[dict], K: np.ndarray, masks: list[np.ndarray]) -> np.ndarray:
    """Outlines of the visible masks, cuboids (front face in red) and XYZ axes (red, green, blue) on `rgb`."""
    out = rgb.copy()
    for mask in masks:
        out = draw_mask_outline(out, mask, (255, 255, 0), 1)
    for obj, g in zip(dope["objects"], gt):
        draw_cuboid(out, np.array(obj["projected_cuboid"])[:8])
        T = make_T(np.array(g["cam_R_m2c"]).reshape(3, 3), np.array(g["cam_t_m2c"]) / 1000.0)
        length = 0.5 * np.linalg.norm(np.array(obj["cuboid"][0]) - np.array(obj["cuboid"][6])) / 100.0
        draw_axes(out, K, T, length)
    return out


def write_contact_sheet(root: Path, frames: int, chunk_size: int, fmt: str, count: int = 12, seed: int = 0) -> Path:
    """Draw `count` random frames of the dataset in `root` into root/contact_sheet.png."""
    picks = sorted(np.random.default_rng(seed).choice(frames, size=min(count, frames), replace=False))
    images, labels = [], []
    for frame in picks:
        chunk, im = frame_location(int(frame), chunk_size)
        base = root / chunk
        dope = json.loads((base / "rgb" / f"{im:06d}.json").read_text())
        gt = json.loads((base / "scene_gt.json").read_text())[str(im)]
        K = np.array(json.loads((base / "scene_camera.json").read_text())[str(im)]["cam_K"]).reshape(3, 3)
        masks = [read_png(base / "mask_visib" / f"{im:06d}_{k:06d}.png") > 0 for k in range(len(gt))]
        images.append(draw_frame(read_png(base / "rgb" / rgb_name(im, fmt)), dope, gt, K, masks))
        labels.append(f"frame {int(frame)}")
    sheet = contact_sheet(images, labels, thumb_width=min(480, images[0].shape[1]))
    write_png(root / "contact_sheet.png", sheet)
    return root / "contact_sheet.png"
