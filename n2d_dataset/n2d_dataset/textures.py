"""Random pictures for domain randomisation, in plain numpy and OpenCV (no bpy): noise-and-shapes images for
distractor and floor surfaces, and printed fiducial sheets (ChArUco boards, ArUco grids)."""

from __future__ import annotations

import cv2
import numpy as np


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
