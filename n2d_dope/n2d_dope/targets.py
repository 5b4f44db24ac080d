"""Training targets of DOPE: Gaussian belief maps of the 9 keypoints and affinity fields towards the centroid.

Maps have output stride 8. Pixel coordinates follow OpenCV (the centre of pixel (0, 0) is at (0, 0)); map cell j
covers input pixels 8j .. 8j+7, so its centre sits at input pixel 8j + 3.5. `to_map` and `to_image` are the one
place this convention lives; training targets and the peak finder both use them.
"""

from __future__ import annotations

import numpy as np

from n2d_dope.network import AFFINITIES, BELIEFS, STRIDE

CENTROID = BELIEFS - 1
"""Index of the centroid among the 9 keypoints (DOPE order: 8 corners, then the centroid)."""


def to_map(points_px: np.ndarray) -> np.ndarray:
    """Input-image pixel coordinates -> map-cell coordinates."""
    return (np.asarray(points_px, dtype=np.float64) - (STRIDE - 1) / 2) / STRIDE


def to_image(points_map: np.ndarray) -> np.ndarray:
    """Map-cell coordinates -> input-image pixel coordinates."""
    return np.asarray(points_map, dtype=np.float64) * STRIDE + (STRIDE - 1) / 2


def make_targets(instances: list[np.ndarray], visible: list[np.ndarray], map_size: tuple[int, int],
                 sigma_cells: float, affinity_radius_cells: float) -> tuple[np.ndarray, np.ndarray]:
    """Belief maps (9 x h x w) and affinity fields (16 x h x w) for the instances of one image.

    `instances`: per instance a 9 x 2 array of keypoints in input pixels (8 corners + centroid); `visible`: per
    instance 9 booleans, False for keypoints that get no target (e.g. hidden ones when configured so). Beliefs
    are the maximum of the instances' Gaussians (peak 1); the affinity of corner k near that corner is the unit
    vector from the corner to its instance's centroid (in map cells, x then y), as in DOPE.
    """
    w, h = map_size
    beliefs = np.zeros((BELIEFS, h, w), np.float32)
    affinities = np.zeros((AFFINITIES, h, w), np.float32)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    reach = 3.0 * sigma_cells
    for points, vis in zip(instances, visible):
        cells = to_map(points)
        for k, ((x, y), ok) in enumerate(zip(cells, vis)):
            if not ok or not (-reach <= x < w + reach and -reach <= y < h + reach):
                continue
            d2 = (xs - x) ** 2 + (ys - y) ** 2
            np.maximum(beliefs[k], np.exp(-d2 / (2 * sigma_cells ** 2)), out=beliefs[k])
            if k == CENTROID:
                continue
            direction = cells[CENTROID] - cells[k]
            norm = np.linalg.norm(direction)
            if norm < 1e-6:
                continue
            near = d2 <= affinity_radius_cells ** 2
            affinities[2 * k][near] = direction[0] / norm
            affinities[2 * k + 1][near] = direction[1] / norm
    return beliefs, affinities
