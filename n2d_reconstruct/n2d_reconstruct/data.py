"""A capture session as arrays for reconstruction: undistorted images, masks, intrinsics, poses, split.

Every pose here is `T_turntable_cam` (camera-to-turntable, OpenCV camera axes, metres): the frame the
capture stage made metric and gravity-aligned from the board, so the reconstruction needs no scaling
or manual alignment. Every `holdout_every`-th view is held out of training and only used to measure.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from n2d_common.errors import ContractError
from n2d_common.formats.session import TRUTH_DIR, read_session
from n2d_common.frames import inv_T, transform_points
from n2d_common.images import read_png

MIN_MASK_FRACTION = 0.001
"""A mask covering less of its image than this is empty: the object is missing or segmentation failed."""
MAX_MASK_FRACTION = 0.9
"""A mask covering more of its image than this is full: segmentation took the background too."""


@dataclass
class Views:
    """N views of one camera: images, masks and poses, all undistorted to the pinhole `K`."""

    rgb: np.ndarray
    """N x H x W x 3 uint8 sRGB."""
    masks: np.ndarray
    """N x H x W bool foreground masks."""
    K: np.ndarray
    """3 x 3 intrinsics, OpenCV convention (pixel centres at integer coordinates)."""
    T_turntable_cam: np.ndarray
    """N x 4 x 4 camera poses in the turntable frame (OpenCV camera axes), metres."""
    names: list[str]
    """Image file of each view, relative to the session directory."""
    truth: np.ndarray | None = None
    """N x H x W x 3 uint8 noise-free images of the same views (simulated sessions only), else None."""
    placement: np.ndarray | None = None
    """N placement indices (`n2d_placement` in transforms.json); None: all views of one placement."""

    def __len__(self) -> int:
        return len(self.names)

    @property
    def height(self) -> int:
        return self.rgb.shape[1]

    @property
    def width(self) -> int:
        return self.rgb.shape[2]

    @property
    def pixel_m(self) -> float:
        """The size of a pixel at the turntable centre, metres (median camera distance over the focal length)."""
        return float(np.median(np.linalg.norm(self.T_turntable_cam[:, :3, 3], axis=1))) / float(self.K[0, 0])

    def project(self, view: int, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """N x 2 pixel coordinates (float) and N depths along the optical axis (metres) of N x 3 turntable-frame
        points in view `view`."""
        cam = transform_points(inv_T(self.T_turntable_cam[view]), points)
        return cam[:, :2] / cam[:, 2:] * self.K[[0, 1], [0, 1]] + self.K[:2, 2], cam[:, 2]

    def pixels(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The nearest pixel (N x 2 ints, column and row) of each pixel coordinate, and whether it is in the image."""
        px = np.rint(uv).astype(np.int64)
        return px, (px >= 0).all(1) & (px[:, 0] < self.width) & (px[:, 1] < self.height)

    @property
    def placements(self) -> int:
        """How many placements the views come from."""
        return 1 if self.placement is None or not len(self) else int(self.placement.max()) + 1

    def subset(self, index) -> Views:
        """The views at `index` (a list of ints or a boolean array)."""
        index = np.asarray(index)
        return Views(self.rgb[index], self.masks[index], self.K, self.T_turntable_cam[index],
                     [self.names[i] for i in np.arange(len(self))[index]],
                     None if self.truth is None else self.truth[index],
                     None if self.placement is None else self.placement[index])

    def of_placement(self, placement: int) -> Views:
        """The views of one placement (all of them for placement 0 of a one-placement session)."""
        if self.placement is None:
            return self if placement == 0 else self.subset(np.zeros(len(self), dtype=bool))
        return self.subset(self.placement == placement)


@dataclass
class SessionData:
    """A capture session split into training and held-out views."""

    directory: Path
    train: Views
    heldout: Views
    plate_radius_m: float
    """Radius of the turntable plate: the object stands inside this circle."""
    plates: np.ndarray | None = None
    """P x 4 plate planes (n, d) of a fused session of several placements, first placement's frame (the object
    stands at n . p + d >= 0 on each); None: the one turntable plate, z >= 0."""
    registration: dict | None = None
    """How the placements were registered (several placements only)."""


def load_session(directory: str | Path, *, holdout_every: int = 8, min_views: int = 8) -> SessionData:
    """Read a complete capture session, check it is usable, undistort it and split it.

    Raises ContractError (with a hint) for an incomplete or foreign session, too few views, missing
    masks or poses, and masks that are empty or cover almost the whole image.
    """
    session = read_session(directory)
    directory = Path(directory)
    if len(session.views) < min_views:
        raise ContractError(f"{directory} has {len(session.views)} views; reconstruction needs at least {min_views}",
                            f"capture more views (n2d capture ... --set sweep.views={max(36, min_views)})")
    rgb, masks, poses = [], [], []
    for view in session.views:
        if view.mask is None or not view.mask.is_file():
            raise ContractError(f"{view.image.name} has no mask in {directory}",
                                "re-run the capture processing, which writes masks/ next to images/")
        T = np.asarray(view.T_turntable_cam if view.T_turntable_cam is not None else np.nan, dtype=float)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise ContractError(f"{view.image.name} has no valid camera pose in transforms.json",
                                "re-run the capture processing; every view needs a transform_matrix")
        image, mask = read_png(view.image), read_png(view.mask)
        for name, img in ((view.image, image), (view.mask, mask)):
            if img.shape[:2] != (session.height, session.width) or img.dtype != np.uint8:
                raise ContractError(f"{name.relative_to(directory)} is {img.shape[1]}x{img.shape[0]} "
                                    f"({img.dtype}), the session's camera {session.width}x{session.height} (uint8)",
                                    "the session is damaged: capture it again")
        if image.ndim != 3 or image.shape[2] < 3:
            raise ContractError(f"{view.image.relative_to(directory)} is not a colour image",
                                "the session is damaged: capture it again")
        image = image[..., :3]
        mask = (mask[..., 0] if mask.ndim == 3 else mask) > 127
        fraction = mask.mean()
        if not MIN_MASK_FRACTION <= fraction <= MAX_MASK_FRACTION:
            state = "empty" if fraction < MIN_MASK_FRACTION else "full"
            raise ContractError(f"the mask of {view.image.name} is {state} ({100 * fraction:.2f} % of the image)",
                                "check the object is on the plate and in view; re-capture the empty-plate sweep "
                                "if the background changed")
        rgb.append(image)
        masks.append(mask)
        poses.append(T)
    K, rgb, masks = _undistort(session.K, session.dist, np.stack(rgb), np.stack(masks))
    truth = None
    if all(v.truth is not None for v in session.views):
        truth_rgb = [read_png(v.truth) for v in session.views]
        if any(t.shape != rgb[0].shape or t.dtype != np.uint8 for t in truth_rgb):
            raise ContractError(f"the truth images of {directory} do not match its images",
                                f"the session is damaged: render it again, or delete {TRUTH_DIR}/")
        truth = _undistort(session.K, session.dist, np.stack(truth_rgb), masks)[1]
    names = [str(v.image.relative_to(directory)) for v in session.views]
    placement = np.array([v.placement for v in session.views]) if session.placements > 1 else None
    views = Views(rgb, masks, K, np.stack(poses), names, truth, placement)
    heldout = np.zeros(len(views), dtype=bool)
    if holdout_every > 0:
        heldout[holdout_every // 2::holdout_every] = True
    radius = _plate_diameter_m(directory / "capture.json") / 2
    return SessionData(directory, views.subset(~heldout), views.subset(heldout), float(radius))


def _plate_diameter_m(path: Path) -> float:
    """The plate diameter capture.json records (0.3 m for a session without one)."""
    if not path.is_file():
        return 0.3
    try:
        value = json.loads(path.read_text()).get("board", {}).get("plate_diameter_m", 0.3)
        if isinstance(value, bool) or not 0 < float(value) < 100:
            raise ValueError(value)
        return float(value)
    except (OSError, ValueError, TypeError, AttributeError) as exc:
        raise ContractError(f"{path} is malformed ({type(exc).__name__}: {exc})",
                            "the session is damaged: capture it again, or restore capture.json") from None


def _undistort(K: np.ndarray, dist: np.ndarray, rgb: np.ndarray, masks: np.ndarray):
    """Images and masks resampled to the distortion-free pinhole camera with the same K."""
    if not np.any(dist):
        return K, rgb, masks
    h, w = rgb.shape[1:3]
    maps = cv2.initUndistortRectifyMap(K, dist, None, K, (w, h), cv2.CV_32FC1)
    rgb = np.stack([cv2.remap(im, *maps, cv2.INTER_LINEAR) for im in rgb])
    masks = np.stack([cv2.remap(m.astype(np.uint8), *maps, cv2.INTER_NEAREST) > 0 for m in masks])
    return K, rgb, masks
