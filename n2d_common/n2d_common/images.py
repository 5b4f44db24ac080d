"""Pictures people look at (contact sheets of frames with labels, mask outlines and overlays, RGB uint8) and the
colour helpers of the renderers (sRGB encoding, exposure, random colours, light temperatures)."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from n2d_common.contracts import atomic_write_bytes
from n2d_common.errors import ContractError


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """The sRGB encoding (values in [0, 1]) of linear RGB in [0, 1]."""
    return np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(linear, 1 / 2.4) - 0.055)


def srgb_to_linear(c) -> tuple[float, ...]:
    """Linear values of sRGB-encoded colour components in [0, 1]."""
    c = np.asarray(c, dtype=float)
    return tuple(np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4))


def random_color(rng: np.random.Generator) -> tuple[float, ...]:
    """A random linear colour, saturated or grey alike."""
    hsv = np.uint8([[[rng.uniform(0, 180), rng.uniform(0, 255), rng.uniform(20, 255)]]])
    return srgb_to_linear(cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0] / 255)


def kelvin_to_rgb(kelvin: float) -> tuple[float, float, float]:
    """Approximate linear RGB (max 1) of a black body at `kelvin` (Tanner Helland's fit, 1000-40000 K)."""
    t = np.clip(kelvin, 1000.0, 40000.0) / 100.0
    r = 255.0 if t <= 66 else 329.698727446 * (t - 60) ** -0.1332047592
    g = 99.4708025861 * np.log(t) - 161.1195681661 if t <= 66 else 288.1221695283 * (t - 60) ** -0.0755148492
    b = 255.0 if t >= 66 else (0.0 if t <= 19 else 138.5177312231 * np.log(t - 10) - 305.0447927307)
    rgb = np.array(srgb_to_linear(np.clip([r, g, b], 0, 255) / 255.0))
    return tuple(float(v) for v in rgb / rgb.max())


def auto_exposure(linear: np.ndarray, key: float = 0.18) -> float:
    """Exposure correction in stops that brings the image's log-average luminance to `key`, as a camera's
    auto exposure would (clipped to +-4 stops)."""
    lum = linear @ np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
    mean = float(np.exp(np.log(np.maximum(lum, 1e-4)).mean()))
    return float(np.clip(np.log2(key / mean), -4.0, 4.0))


def to_srgb8(linear: np.ndarray, exposure_ev: float = 0.0) -> np.ndarray:
    """8-bit sRGB (view transform "Standard") of linear RGB after an exposure correction in stops."""
    linear = np.clip(linear * 2.0 ** exposure_ev, 0.0, 1.0)
    return np.round(linear_to_srgb(linear) * 255).astype(np.uint8)


def draw_mask_outline(rgb: np.ndarray, mask: np.ndarray, color=(0, 255, 0), thickness: int = 1) -> np.ndarray:
    """A copy of `rgb` with the outline of boolean `mask` drawn on it."""
    out = rgb.copy()
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(out, contours, -1, color, thickness, lineType=cv2.LINE_AA)
    return out


CUBOID_EDGES = ((0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4), (0, 4), (1, 5), (2, 6), (3, 7))
"""Cuboid edges between keypoints in DOPE order (front face 0-3, rear face 4-7)."""
_FRONT = (0, 1, 2, 3)


def draw_cuboid(rgb: np.ndarray, points_px: np.ndarray, front=(255, 40, 40), rest=(40, 255, 40),
                thickness: int = 1) -> None:
    """Draw the cuboid with keypoints `points_px` (8 corners in DOPE order, in pixels) onto `rgb`, in place;
    edges touching a missing (NaN) corner are skipped."""
    pts = np.asarray(points_px, dtype=float)
    for a, b in CUBOID_EDGES:
        if np.isfinite(pts[[a, b]]).all():
            color = front if a in _FRONT and b in _FRONT else rest
            cv2.line(rgb, tuple(np.round(pts[a]).astype(int)), tuple(np.round(pts[b]).astype(int)), color,
                     thickness, cv2.LINE_AA)


def draw_axes(rgb: np.ndarray, K: np.ndarray, T_cam_obj: np.ndarray, length_m: float, thickness: int = 2) -> None:
    """Draw the object's X, Y, Z axes (red, green, blue) of `length_m` onto `rgb`, in place."""
    from n2d_common.frames import project

    if T_cam_obj[2, 3] <= 0:
        return
    o, x, y, z = np.round(project(K, T_cam_obj, np.vstack([np.zeros(3), np.eye(3) * length_m]))).astype(int)
    for end, color in ((x, (255, 0, 0)), (y, (0, 255, 0)), (z, (0, 0, 255))):
        cv2.line(rgb, tuple(o), tuple(end), color, thickness, cv2.LINE_AA)


def contact_sheet(images: list[np.ndarray], labels: list[str] | None = None, cols: int | None = None,
                  thumb_width: int = 320) -> np.ndarray:
    """Tile RGB images into one sheet, each scaled to `thumb_width` with its label in a corner."""
    if not images:
        raise ValueError("contact_sheet: no images")
    cols = cols or math.ceil(math.sqrt(len(images)))
    rows = math.ceil(len(images) / cols)
    h0, w0 = images[0].shape[:2]
    tw, th = thumb_width, round(thumb_width * h0 / w0)
    sheet = np.full((rows * th + (rows + 1) * 4, cols * tw + (cols + 1) * 4, 3), 24, np.uint8)
    for i, img in enumerate(images):
        thumb = cv2.resize(img, (tw, th), interpolation=cv2.INTER_AREA)
        if labels:
            cv2.putText(thumb, labels[i], (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 3, cv2.LINE_AA)
            cv2.putText(thumb, labels[i], (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
        r, c = divmod(i, cols)
        y, x = 4 + r * (th + 4), 4 + c * (tw + 4)
        sheet[y:y + th, x:x + tw] = thumb
    return sheet


def write_png(path: str | Path, rgb: np.ndarray) -> None:
    """Atomically write an RGB (or single-channel) uint8 image as PNG."""
    img = rgb if rgb.ndim == 2 else cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".png", img)
    if not ok:
        raise OSError(f"could not encode {path} as PNG")
    atomic_write_bytes(path, buf.tobytes())


_SIGNATURES = {".png": (b"\x89PNG\r\n\x1a\n", b"IEND\xaeB`\x82"), ".jpg": (b"\xff\xd8", b"\xff\xd9"),
               ".jpeg": (b"\xff\xd8", b"\xff\xd9")}


def looks_complete(path: str | Path) -> bool:
    """Whether a PNG or JPEG file starts and ends as one does (its signature, PNG's IEND chunk, JPEG's end-of-image
    marker): a cheap test, reading a few bytes, that catches truncated, empty and garbage files."""
    head, tail = _SIGNATURES[Path(path).suffix.lower()]
    try:
        with open(path, "rb") as f:
            start = f.read(len(head))
            f.seek(0, 2)
            size = f.tell()
            f.seek(max(0, size - 16))
            end = f.read()
    except OSError:
        return False
    return start == head and tail in end


def read_png(path: str | Path) -> np.ndarray:
    """RGB uint8 (or single-channel) image from a PNG; ContractError when it is missing or cannot be decoded."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        why = "it is missing" if not Path(path).is_file() else "it is truncated or not an image"
        raise ContractError(f"cannot read image {path}: {why}",
                            "the directory is damaged: run the stage that wrote it again")
    return img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
