"""Random colours and pictures for domain randomisation, in plain numpy and OpenCV (no bpy): colours and light
temperatures, noise-and-shapes images for
distractor and floor surfaces, and printed fiducial sheets (ChArUco boards, ArUco grids)."""

from __future__ import annotations

import cv2
import numpy as np


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


def random_image(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """A random picture made on the fly: coloured noise blobs with shapes and strokes over them."""
    low = rng.integers(0, 256, (rng.integers(2, 9), rng.integers(2, 9), 3), dtype=np.uint8)
    img = cv2.resize(low, (size, size), interpolation=cv2.INTER_CUBIC)
    for _ in range(rng.integers(3, 15)):
        color = tuple(int(c) for c in rng.integers(0, 256, 3))
        x, y = (int(v) for v in rng.integers(0, size, 2))
        r = int(rng.integers(4, size // 4))
        if rng.random() < 0.4:
            cv2.circle(img, (x, y), r, color, -1, cv2.LINE_AA)
        elif rng.random() < 0.6:
            cv2.rectangle(img, (x, y), (x + r, y + r // 2), color, -1)
        else:
            x2, y2 = (int(v) for v in rng.integers(0, size, 2))
            cv2.line(img, (x, y), (x2, y2), color, int(rng.integers(1, 6)), cv2.LINE_AA)
    return img


FIDUCIAL_DICTIONARIES = ("DICT_4X4_100", "DICT_5X5_100", "DICT_6X6_250", "DICT_APRILTAG_36h11")
"""ArUco dictionaries a random fiducial sheet draws its markers from."""


def random_fiducial_sheet(rng: np.random.Generator, px_per_square: int = 64) -> np.ndarray:
    """A printed calibration sheet: a ChArUco board or an ArUco marker grid of random size and dictionary,
    with a white paper margin, as a grey uint8 image."""
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, str(rng.choice(FIDUCIAL_DICTIONARIES))))
    nx, ny = (int(n) for n in rng.integers(4, 10, 2))
    size = (nx * px_per_square, ny * px_per_square)
    if rng.random() < 0.7:
        board = cv2.aruco.CharucoBoard((nx, ny), 1.0, rng.uniform(0.55, 0.78), dictionary)
    else:
        board = cv2.aruco.GridBoard((nx, ny), 1.0, rng.uniform(0.2, 0.6), dictionary)
    return board.generateImage(size, marginSize=int(rng.integers(4, px_per_square // 2)), borderBits=1)
