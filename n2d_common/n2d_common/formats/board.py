"""The printed ChArUco board that lies on the turntable plate: its spec, printable image and place on the plate.

Board frame (OpenCV's): origin at the outer corner of square (0, 0), x along `squares_x`, y along
`squares_y`, z into the board. Plate frame: origin at the plate centre on its top surface (the board's
printed surface), Z up along the rotation axis. The board lies face up, centred on the plate, with
its x axis along plate +X, so its y axis runs along plate -Y and its z axis along plate -Z.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from n2d_common.config import from_dict, to_dict
from n2d_common.frames import make_T


@dataclass
class BoardSpec:
    """A ChArUco board printed on a sheet and laid on the turntable plate."""

    squares_x: int = 7
    """Chessboard squares along the board's x axis."""
    squares_y: int = 7
    """Chessboard squares along the board's y axis."""
    square_m: float = 0.030
    """Side of one chessboard square, metres."""
    marker_m: float = 0.022
    """Side of one ArUco marker (inside a white square), metres."""
    dictionary: str = "DICT_5X5_100"
    """Name of the predefined ArUco dictionary in cv2.aruco, e.g. DICT_5X5_100."""
    margin_m: float = 0.005
    """White paper around the outermost squares, metres (printed sheet = board + 2 margins)."""
    plate_diameter_m: float = 0.32
    """Diameter of the turntable plate the board lies on, metres."""

    def __post_init__(self):
        if self.squares_x < 3 or self.squares_y < 3:
            raise ValueError(f"a ChArUco board needs at least 3x3 squares, "
                             f"got {self.squares_x}x{self.squares_y}")
        if not 0 < self.marker_m < self.square_m:
            raise ValueError(f"marker_m must be in (0, square_m={self.square_m}), got {self.marker_m}")
        if self.margin_m < 0:
            raise ValueError(f"margin_m must be >= 0, got {self.margin_m}")
        if not self.dictionary.startswith("DICT_") or not hasattr(cv2.aruco, self.dictionary):
            raise ValueError(f"unknown ArUco dictionary {self.dictionary!r}; e.g. DICT_5X5_100")
        markers = self.squares_x * self.squares_y // 2
        available = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary)).bytesList.shape[0]
        if markers > available:
            raise ValueError(f"{self.squares_x}x{self.squares_y} squares need {markers} markers, "
                             f"{self.dictionary} has {available}")
        w, h = self.sheet_m
        if math.hypot(w, h) > self.plate_diameter_m:
            raise ValueError(f"the {w:.3f}x{h:.3f} m sheet does not fit on a plate of diameter "
                             f"{self.plate_diameter_m} m (its diagonal is {math.hypot(w, h):.3f} m)")

    @property
    def size_m(self) -> tuple[float, float]:
        """(width, height) of the squares area in metres, along board x and y."""
        return self.squares_x * self.square_m, self.squares_y * self.square_m

    @property
    def sheet_m(self) -> tuple[float, float]:
        """(width, height) of the printed sheet in metres, margins included."""
        w, h = self.size_m
        return w + 2 * self.margin_m, h + 2 * self.margin_m

    def cv_board(self) -> cv2.aruco.CharucoBoard:
        """The OpenCV board object (units: metres)."""
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        squares = (self.squares_x, self.squares_y)
        return cv2.aruco.CharucoBoard(squares, self.square_m, self.marker_m, dictionary)

    def to_dict(self) -> dict:
        """JSON-safe spec, e.g. for capture.json."""
        return to_dict(self)

    @classmethod
    def from_dict(cls, data: dict) -> BoardSpec:
        """The spec written by `to_dict`; unknown keys or bad values raise ConfigError."""
        return from_dict(cls, data)


def board_image(spec: BoardSpec, px_per_m: float) -> np.ndarray:
    """The board's squares area as a grey uint8 image, row 0 at board y = 0, column 0 at board x = 0.

    The image spans exactly the squares area (no margin) with a whole number of pixels per square,
    the nearest to `px_per_m`. Square boundaries therefore fall on pixel edges: board point
    (x, y) metres is at pixel (x * s - 0.5, y * s - 0.5) in OpenCV's pixel-centre convention, with
    s = image width / board width.
    """
    px_per_square = max(1, round(spec.square_m * px_per_m))
    size = (spec.squares_x * px_per_square, spec.squares_y * px_per_square)
    return spec.cv_board().generateImage(size, marginSize=0, borderBits=1)


def T_plate_board(spec: BoardSpec) -> np.ndarray:
    """4x4 pose of the board frame in the plate frame (board centred and face up on the plate)."""
    w, h = spec.size_m
    R = np.diag([1.0, -1.0, -1.0])
    return make_T(R, [-w / 2, h / 2, 0.0])
