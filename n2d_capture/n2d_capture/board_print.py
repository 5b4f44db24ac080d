"""Print files of the ChArUco board: a PDF at exact physical size, a PNG with its resolution, and board.json.

The PDF is written here (one page, one Flate-compressed grey image, one caption line in the standard
Helvetica font), so it needs no PDF library. Its page is the sheet (board plus margins); the board
image is placed at exactly the spec's size, whatever its pixel count. When the bottom margin is
too narrow for the caption, the page grows downwards instead, and the board keeps its size.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np

from n2d_common.contracts import atomic_write_bytes, atomic_write_json
from n2d_common.formats.board import BoardSpec, board_image

POINTS_PER_M = 72 / 0.0254
"""PDF user-space units (points) per metre."""
CAPTION_ROOM_M = 0.004
"""Height kept below the board for the caption line, metres (the bottom margin when it is wider)."""


def write_board_print(spec: BoardSpec, out_dir: str | Path, dpi: int = 300) -> dict[str, Path]:
    """Write `board.pdf`, `board.png` and `board.json` for `spec` into `out_dir`; returns their paths.

    The PNG is the whole sheet at about `dpi`, rounded so one square is a whole number of pixels; its
    pHYs chunk holds that exact resolution, so viewers that honour it print it at size. board.json
    is the spec (`BoardSpec.to_dict`), for the capture and reconstruction stages.
    """
    if dpi < 50:
        raise ValueError(f"dpi must be >= 50, got {dpi}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    squares = board_image(spec, dpi / 0.0254)
    px_per_m = squares.shape[1] / spec.size_m[0]
    margin_px = round(spec.margin_m * px_per_m)
    sheet = cv2.copyMakeBorder(squares, margin_px, margin_px, margin_px, margin_px, cv2.BORDER_CONSTANT, value=255)
    ok, png = cv2.imencode(".png", sheet)
    if not ok:
        raise OSError("could not encode the board as PNG")
    paths = {"pdf": out / "board.pdf", "png": out / "board.png", "json": out / "board.json"}
    atomic_write_bytes(paths["pdf"], board_pdf(spec, squares))
    atomic_write_bytes(paths["png"], png_with_resolution(png.tobytes(), round(px_per_m)))
    atomic_write_json(paths["json"], spec.to_dict())
    return paths


def caption(spec: BoardSpec) -> str:
    """The line printed under the board: what it is and how to check the print's scale."""
    square_mm, marker_mm = spec.square_m * 1000, spec.marker_m * 1000
    return (f"ChArUco {spec.squares_x}x{spec.squares_y} squares, square {square_mm:g} mm, marker {marker_mm:g} mm, "
            f"{spec.dictionary} - print at 100 % / actual size; measure one square: should be {square_mm:g} mm")


def board_pdf(spec: BoardSpec, squares: np.ndarray) -> bytes:
    """A one-page PDF: the grey image `squares` (the board's squares area) at the spec's physical size."""
    w_m, h_m = spec.size_m
    below_m = max(spec.margin_m, CAPTION_ROOM_M)
    page_w, page_h = (spec.sheet_m[0] * POINTS_PER_M, (h_m + spec.margin_m + below_m) * POINTS_PER_M)
    x0, y0 = spec.margin_m * POINTS_PER_M, below_m * POINTS_PER_M
    text = caption(spec)
    # Helvetica averages under 0.55 em per character in this text: shrink the font until the line fits.
    size = min(7.0, 0.55 * y0, 0.95 * page_w / (0.55 * len(text)))
    escaped = text.replace("\\", "\\\\").replace("(", "\\(").replace(")", "\\)")
    content = (f"q {_num(w_m * POINTS_PER_M)} 0 0 {_num(h_m * POINTS_PER_M)} {_num(x0)} {_num(y0)} cm /Im0 Do Q\n"
               f"BT /F1 {_num(size)} Tf {_num(x0)} {_num(y0 / 2 - 0.35 * size)} Td ({escaped}) Tj ET\n").encode()
    height, width = squares.shape
    image = zlib.compress(np.ascontiguousarray(squares, dtype=np.uint8).tobytes(), 9)
    objects = [
        b"<< /Type /Catalog /Pages 2 0 R >>",
        b"<< /Type /Pages /Kids [3 0 R] /Count 1 >>",
        (f"<< /Type /Page /Parent 2 0 R /MediaBox [0 0 {_num(page_w)} {_num(page_h)}] "
         f"/Resources << /XObject << /Im0 5 0 R >> /Font << /F1 6 0 R >> >> /Contents 4 0 R >>").encode(),
        _stream(b"", content),
        _stream(f"/Type /XObject /Subtype /Image /Width {width} /Height {height} /ColorSpace /DeviceGray "
                f"/BitsPerComponent 8 /Interpolate false /Filter /FlateDecode".encode(), image),
        b"<< /Type /Font /Subtype /Type1 /BaseFont /Helvetica /Encoding /WinAnsiEncoding >>",
    ]
    out = bytearray(b"%PDF-1.4\n%\xe2\xe3\xcf\xd3\n")
    offsets = []
    for number, body in enumerate(objects, start=1):
        offsets.append(len(out))
        out += f"{number} 0 obj\n".encode() + body + b"\nendobj\n"
    xref = len(out)
    out += f"xref\n0 {len(objects) + 1}\n0000000000 65535 f \n".encode()
    out += b"".join(f"{o:010d} 00000 n \n".encode() for o in offsets)
    out += f"trailer\n<< /Size {len(objects) + 1} /Root 1 0 R >>\nstartxref\n{xref}\n%%EOF\n".encode()
    return bytes(out)


def png_with_resolution(png: bytes, px_per_m: int) -> bytes:
    """`png` with a pHYs chunk (pixels per metre, both axes) right after IHDR; cv2 does not write one."""
    ihdr_end = 8 + 8 + 13 + 4  # signature, IHDR length + type, IHDR data, CRC
    if png[:8] != b"\x89PNG\r\n\x1a\n" or png[12:16] != b"IHDR":
        raise ValueError("not a PNG")
    data = b"pHYs" + struct.pack(">IIB", px_per_m, px_per_m, 1)
    chunk = struct.pack(">I", 9) + data + struct.pack(">I", zlib.crc32(data))
    return png[:ihdr_end] + chunk + png[ihdr_end:]


def _stream(dictionary: bytes, data: bytes) -> bytes:
    return b"<< " + dictionary + f" /Length {len(data)} >>\nstream\n".encode() + data + b"\nendstream"


def _num(value: float) -> str:
    """A PDF real: 4 decimals, trailing zeros dropped."""
    return f"{value:.4f}".rstrip("0").rstrip(".")
