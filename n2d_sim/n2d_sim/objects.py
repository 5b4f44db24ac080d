"""The shipped sample objects: procedurally generated, textured, metric meshes that we own.

Each object is a "model" directory (the contract the reconstruction stage writes): `mesh.obj` +
`mesh.mtl` + `albedo.png` in metres, object frame at the bounding-box centre with Z up as it stands,
`models_info.json` (BOP, millimetres) and an `n2d.json` manifest marking it as ground truth.
Generation is deterministic; regenerate the committed copies with

    python -m n2d_sim.objects --out n2d_sim/n2d_sim/objects
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
from scipy.spatial import ConvexHull

from n2d_common.contracts import atomic_write_bytes, atomic_write_text, read_manifest, write_manifest
from n2d_common.errors import ConfigError

SAMPLE_OBJECTS = ("box", "bottle")
"""Names of the shipped sample objects."""

OBJECTS_DIR = Path(__file__).with_name("objects")

BOX_SIZE_MM = (90.0, 60.0, 140.0)
"""Printed cardboard box: width (x, front face), depth (y), height (z)."""
BOTTLE_DIAMETER_MM = 70.0
BOTTLE_HEIGHT_MM = 150.0
BOTTLE_SEGMENTS = 48
"""Facets around the bottle's axis (a multiple of 4 keeps the bounding box at exactly +-radius)."""

FONT = cv2.FONT_HERSHEY_DUPLEX
FONT_BOLD = cv2.FONT_HERSHEY_TRIPLEX
FONT_SMALL = cv2.FONT_HERSHEY_SIMPLEX


def sample_object_dir(name: str) -> Path:
    """Directory of the shipped sample object `name` (one of SAMPLE_OBJECTS)."""
    if name not in SAMPLE_OBJECTS:
        raise ConfigError(f"unknown sample object {name!r}", f"choose one of {', '.join(SAMPLE_OBJECTS)}")
    return OBJECTS_DIR / name


class _MeshBuilder:
    """Triangles with separately indexed positions, UVs and normals (as OBJ stores them)."""

    def __init__(self):
        self.v: dict[tuple, int] = {}
        self.vt: dict[tuple, int] = {}
        self.vn: dict[tuple, int] = {}
        self.faces: list[tuple[tuple[int, int, int], ...]] = []

    @staticmethod
    def _index(table: dict, value, decimals: int) -> int:
        key = tuple(float(x) + 0.0 for x in np.round(np.asarray(value, dtype=float), decimals))
        return table.setdefault(key, len(table))

    def corner(self, p, uv, n) -> tuple[int, int, int]:
        return self._index(self.v, p, 7), self._index(self.vt, uv, 6), self._index(self.vn, n, 5)

    def tri(self, a, b, c) -> None:
        self.faces.append((a, b, c))

    def positions(self) -> np.ndarray:
        return np.array(list(self.v), dtype=float)

    def obj_text(self, name: str, label: str = "sample object") -> str:
        lines = [f"# n2d {label} '{name}': metres, origin at the bounding-box centre, Z up",
                 "mtllib mesh.mtl", f"o {name}"]
        lines += [f"v {x:.7f} {y:.7f} {z:.7f}" for x, y, z in self.v]
        lines += [f"vt {u:.6f} {v:.6f}" for u, v in self.vt]
        lines += [f"vn {x:.5f} {y:.5f} {z:.5f}" for x, y, z in self.vn]
        lines += [f"usemtl {name}", "s off"]
        lines += ["f " + " ".join(f"{v + 1}/{t + 1}/{n + 1}" for v, t, n in f) for f in self.faces]
        return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------------------
# Printing helpers (RGB uint8 canvases, deterministic)


def _text(img, text, org, scale, color, thickness=1, font=FONT):
    cv2.putText(img, text, (int(org[0]), int(org[1])), font, scale, color, thickness, cv2.LINE_AA)


def _text_fit(img, text, x, y, w, h, color, thickness=2, font=FONT_BOLD):
    """Draw `text` as large as fits in the box (x, y, w, h), centred."""
    (tw, th), base = cv2.getTextSize(text, font, 1.0, thickness)
    scale = min(w / tw, h / (th + base))
    (tw, th), base = cv2.getTextSize(text, font, scale, thickness)
    _text(img, text, (x + (w - tw) / 2, y + (h + th - base) / 2), scale, color, thickness, font)


def _text_lines(img, lines, x, y, dy, scale, color, font=FONT_SMALL):
    for i, line in enumerate(lines):
        _text(img, line, (x, y + i * dy), scale, color, 1, font)


def _barcode(img, x, y, w, h, rng):
    """An EAN-like barcode: guard bars, random bars of 1-3 modules and digits below."""
    modules = 95
    m = w / modules
    cv2.rectangle(img, (x - 4, y - 4), (x + w + 4, y + h + 16), (255, 255, 255), -1)
    bits = []
    for i in range(modules):
        guard = i < 3 or i >= modules - 3 or 45 <= i < 50
        bits.append((i % 2 == 0) if guard else None)
    i = 0
    while i < modules:
        if bits[i] is None:
            run = int(rng.integers(1, 4))
            value = bool(rng.integers(0, 2))
            for k in range(i, min(i + run, modules)):
                if bits[k] is None:
                    bits[k] = value
            i += run
        else:
            i += 1
    for i, bit in enumerate(bits):
        if bit:
            x0 = round(x + i * m)
            x1 = max(x0 + 1, round(x + (i + 1) * m))
            cv2.rectangle(img, (x0, y), (x1 - 1, y + h), (0, 0, 0), -1)
    digits = "".join(str(int(d)) for d in rng.integers(0, 10, 13))
    _text_fit(img, f"{digits[0]} {digits[1:7]} {digits[7:]}", x, y + h + 2, w, 13, (0, 0, 0), 1, FONT_SMALL)


def _blocks(img, x, y, size, rng, cells=21):
    """A QR-like square of random modules with three finder patterns."""
    cell = size / cells
    grid = rng.integers(0, 2, (cells, cells)).astype(bool)
    for cx, cy in ((0, 0), (cells - 7, 0), (0, cells - 7)):
        grid[cy:cy + 7, cx:cx + 7] = False
        grid[cy:cy + 7, cx] = grid[cy:cy + 7, cx + 6] = True
        grid[cy, cx:cx + 7] = grid[cy + 6, cx:cx + 7] = True
        grid[cy + 2:cy + 5, cx + 2:cx + 5] = True
    cv2.rectangle(img, (x - 4, y - 4), (round(x + size) + 4, round(y + size) + 4), (255, 255, 255), -1)
    for r, c in zip(*np.nonzero(grid)):
        cv2.rectangle(img, (round(x + c * cell), round(y + r * cell)),
                      (round(x + (c + 1) * cell) - 1, round(y + (r + 1) * cell) - 1), (0, 0, 0), -1)


def _logo(img, cx, cy, r, colors):
    """Concentric rings cut by a triangle: a made-up brand mark."""
    for i, color in enumerate(colors):
        cv2.circle(img, (round(cx), round(cy)), round(r * (1 - 0.22 * i)), color, -1, cv2.LINE_AA)
    tri = np.array([[cx, cy - 0.55 * r], [cx + 0.5 * r, cy + 0.35 * r], [cx - 0.5 * r, cy + 0.35 * r]])
    cv2.fillPoly(img, [np.round(tri).astype(np.int32)], (255, 255, 255), cv2.LINE_AA)


# ---------------------------------------------------------------------------------------------
# The box


def _box_faces(sx, sy, sz):
    """Per face: name, origin corner, right and up unit vectors (right x up = outward normal), size."""
    hx, hy, hz = sx / 2, sy / 2, sz / 2
    X, Y, Z = np.eye(3)
    return [
        ("front", (-hx, -hy, -hz), X, Z, sx, sz),
        ("right", (hx, -hy, -hz), Y, Z, sy, sz),
        ("back", (hx, hy, -hz), -X, Z, sx, sz),
        ("left", (-hx, hy, -hz), -Y, Z, sy, sz),
        ("top", (-hx, -hy, hz), X, Y, sx, sy),
        ("bottom", (-hx, hy, -hz), X, -Y, sx, sy),
    ]


def _draw_box_face(name: str, h: int, w: int, rng) -> np.ndarray:
    teal, orange, cream, ink = (18, 96, 110), (240, 128, 30), (246, 238, 220), (25, 25, 35)
    kraft = (196, 160, 112)
    img = np.zeros((h, w, 3), np.uint8)
    if name == "front":
        img[:] = teal
        img[: h // 5] = orange
        _text_fit(img, "N2D", 10, 8, w - 20, h // 5 - 16, (255, 255, 255), 5)
        _logo(img, w * 0.5, h * 0.36, w * 0.2, [(250, 210, 60), (230, 70, 50), (40, 40, 60)])
        _text_fit(img, "TURNTABLE", 12, int(h * 0.52), w - 24, 34, cream, 2)
        _text_fit(img, "SENSOR KIT", 12, int(h * 0.60), w - 24, 30, (250, 210, 60), 2)
        for i in range(7):  # hexagon "photo" strip
            cx, cy = 22 + i * 42, int(h * 0.74) + (i % 2) * 18
            pts = [(cx + 18 * math.cos(a), cy + 18 * math.sin(a)) for a in np.arange(6) * math.pi / 3]
            color = tuple(int(c) for c in rng.integers(60, 255, 3))
            cv2.fillPoly(img, [np.round(pts).astype(np.int32)], color, cv2.LINE_AA)
        img[int(h * 0.86):] = cream
        _text(img, "Model T-30  |  250 g", (12, h * 0.86 + 26), 0.62, ink, 1)
        _text(img, "made by n2d labs", (12, h * 0.86 + 50), 0.5, teal, 1, FONT_SMALL)
    elif name == "back":
        img[:] = cream
        img[:40] = teal
        _text(img, "CONTENTS", (12, 29), 0.9, (255, 255, 255), 2)
        lines = ["1x rotary plate 320 mm", "1x ChArUco sheet 7x7", "1x servo XL430-W250",
                 "1x USB2 serial adapter", "4x rubber feet", "", "Keep dry. Store between",
                 "5 and 35 degrees C.", "Not a toy. Contains small", "parts. Ages 14+."]
        _text_lines(img, lines, 12, 66, 21, 0.5, ink)
        for i in range(4):
            y = 270 + i * 18
            cv2.line(img, (12, y), (w - 12, y), ink, 1)
            _text(img, f"{['mass', 'volt', 'amp', 'rpm'][i]}", (16, y + 14), 0.45, ink, 1, FONT_SMALL)
            _text(img, f"{int(rng.integers(10, 999))}", (w - 60, y + 14), 0.45, ink, 1, FONT_SMALL)
        _barcode(img, 30, h - 100, w - 60, 62, rng)
    elif name == "right":
        side = np.zeros((w, h, 3), np.uint8)  # the face lying on its side, for vertical text
        side[:] = (250, 210, 60)
        _text_fit(side, "N2D LABS", 14, 10, h - 110, w - 20, (30, 30, 30), 4)
        img = np.ascontiguousarray(np.rot90(side, 3))
        for i in range(0, h, 36):
            cv2.line(img, (0, i), (w, i + 40), orange, 6, cv2.LINE_AA)
        cv2.rectangle(img, (8, h - 70), (w - 8, h - 8), (255, 255, 255), -1)
        _text_fit(img, "3D SCAN", 14, h - 66, w - 28, 54, teal, 2)
    elif name == "left":
        img[:] = (120, 50, 140)
        _blocks(img, 22, 24, w - 44, rng)
        for i in range(6):
            c = (int(rng.integers(120, 255)), int(rng.integers(120, 255)), int(rng.integers(40, 200)))
            cv2.circle(img, (30 + (i % 3) * 68, 230 + (i // 3) * 64), 24, c, -1, cv2.LINE_AA)
            _text_fit(img, "ABCDEF"[i], 18 + (i % 3) * 68, 218 + (i // 3) * 64, 24, 24, (20, 20, 20), 2)
        _text_lines(img, ["scan me", "v1.0", "lot 0427"], 22, h - 90, 26, 0.7, (255, 255, 255), FONT)
    else:
        img[:] = kraft
        cv2.line(img, (0, h // 2), (w, h // 2), (150, 116, 76), 2)
        if name == "top":
            _text_fit(img, "THIS SIDE UP", 20, 10, w - 40, 38, (170, 30, 30), 2)
            for cx in (w * 0.3, w * 0.7):
                pts = np.array([[cx, h * 0.55], [cx - 26, h * 0.8], [cx + 26, h * 0.8]])
                cv2.fillPoly(img, [np.round(pts).astype(np.int32)], (170, 30, 30), cv2.LINE_AA)
                cv2.rectangle(img, (round(cx - 9), round(h * 0.8)), (round(cx + 9), h - 10), (170, 30, 30),
                              -1)
        else:
            _text_lines(img, [f"BATCH {int(rng.integers(1000, 9999))}-{int(rng.integers(10, 99))}",
                              "RECYCLABLE CARDBOARD"], 16, 40, 26, 0.6, ink, FONT)
            cv2.circle(img, (w - 50, h - 50), 30, ink, 2, cv2.LINE_AA)
            _text_fit(img, "PAP", w - 72, h - 62, 44, 24, ink, 1, FONT_SMALL)
    return img


def _make_box() -> tuple[_MeshBuilder, np.ndarray, dict]:
    sx, sy, sz = (s / 1000 for s in BOX_SIZE_MM)
    px_per_m, gap, bleed = 3300.0, 6, 3
    faces = _box_faces(sx, sy, sz)
    sizes = {name: (round(w * px_per_m), round(h * px_per_m)) for name, _, _, _, w, h in faces}
    layout = [["front", "right", "back", "left"], ["top", "bottom"]]
    rects, y = {}, gap
    for row in layout:
        x = gap
        for name in row:
            rects[name] = (x, y) + sizes[name]
            x += sizes[name][0] + gap
        y += max(sizes[name][1] for name in row) + gap
    W = max(r[0] + r[2] for r in rects.values()) + gap
    H = y
    atlas = np.full((H, W, 3), 128, np.uint8)
    rng = np.random.default_rng(20240427)
    mesh = _MeshBuilder()
    for name, origin, right, up, w, h in faces:
        x0, y0, pw, ph = rects[name]
        face = _draw_box_face(name, ph, pw, rng)
        atlas[y0 - bleed:y0 + ph + bleed, x0 - bleed:x0 + pw + bleed] = cv2.copyMakeBorder(
            face, bleed, bleed, bleed, bleed, cv2.BORDER_REPLICATE)
        normal = np.cross(right, up)
        nu, nv = max(1, round(w / 0.01)), max(1, round(h / 0.01))
        grid = {}
        for i in range(nu + 1):
            for j in range(nv + 1):
                a, b = i / nu, j / nv
                p = np.asarray(origin) + a * w * right + b * h * up
                uv = ((x0 + a * pw) / W, 1 - (y0 + (1 - b) * ph) / H)
                grid[i, j] = mesh.corner(p, uv, normal)
        for i in range(nu):
            for j in range(nv):
                mesh.tri(grid[i, j], grid[i + 1, j], grid[i + 1, j + 1])
                mesh.tri(grid[i, j], grid[i + 1, j + 1], grid[i, j + 1])
    material = {"roughness": 0.65, "specular": 0.3}
    return mesh, atlas, material


# ---------------------------------------------------------------------------------------------
# The bottle (a body of revolution with a wrap-around label and a screw cap)


def _bottle_profile_mm() -> np.ndarray:
    """(r, z) polyline from the bottom pole to the top pole, millimetres, z from 0 (standing) up."""
    r = BOTTLE_DIAMETER_MM / 2
    pts = [(0.0, 0.0), (r - 4, 0.0), (r - 1.2, 0.6), (r, 3.0)]
    pts += [(r, z) for z in np.linspace(3.0, 100.0, 11)[1:]]
    for t in np.linspace(0, 1, 9)[1:]:  # shoulder: a smooth S from the body to the neck
        s = 0.5 - 0.5 * math.cos(math.pi * t)
        pts.append((r - (r - 14.5) * s, 100.0 + 24.0 * t))
    pts += [(14.5, 127.0), (17.0, 127.0), (17.0, 129.0)]
    pts += [(17.0, z) for z in np.linspace(129.0, 148.5, 4)[1:]]
    pts += [(16.0, 149.7), (14.0, 150.0), (0.0, 150.0)]
    return np.array(pts)


def _draw_bottle_label(W: int, H: int, z_to_row: Callable[[float], int], rng) -> np.ndarray:
    img = np.zeros((H, W, 3), np.uint8)
    body, cap, white = (70, 150, 205), (200, 40, 40), (248, 248, 244)
    img[:] = body
    top, bottom = z_to_row(92.0), z_to_row(18.0)
    img[top:bottom] = white
    band = (bottom - top) // 7
    img[top:top + band] = (20, 60, 130)
    img[bottom - band:bottom] = (20, 60, 130)
    for x in range(0, W, 24):  # wave pattern on the bands
        cv2.ellipse(img, (x, top + band), (12, 6), 0, 180, 360, (110, 190, 240), 2, cv2.LINE_AA)
        cv2.ellipse(img, (x + 12, bottom - band), (12, 6), 0, 0, 180, (110, 190, 240), 2, cv2.LINE_AA)
    mid_y, mid_h = top + band + 6, bottom - top - 2 * band - 12
    q = W // 4
    _text_fit(img, "AQUA", 20, mid_y, q * 2 - 40, mid_h // 2, (20, 60, 130), 4)
    _text_fit(img, "N2D  still water", 20, mid_y + mid_h // 2, q * 2 - 40, mid_h // 3, (60, 60, 60), 2, FONT)
    _logo(img, q * 2 + q // 2, mid_y + mid_h / 2, mid_h * 0.4,
          [(20, 60, 130), (110, 190, 240), (240, 150, 40)])
    lines = ["per 100 ml:", f"calcium {int(rng.integers(10, 90))} mg",
             f"sodium {int(rng.integers(1, 20))} mg", "500 ml  e"]
    _text_lines(img, lines, 3 * q + 14, mid_y + 18, 24, 0.55, (40, 40, 40))
    _barcode(img, 3 * q + 24, mid_y + 112, q - 48, mid_h - 140, rng)
    for _ in range(60):  # printed bubbles above the label
        x, y = int(rng.integers(0, W)), int(rng.integers(z_to_row(112.0), top - 12))
        cv2.circle(img, (x, y), int(rng.integers(3, 12)), (150, 205, 240), 2, cv2.LINE_AA)
    for x in range(0, W, 16):  # moulded ribs below the label
        cv2.line(img, (x, bottom + 10), (x, z_to_row(5.0)), (55, 125, 180), 3)
    cap_row = z_to_row(128.0)
    img[:cap_row] = cap
    for x in range(0, W, 8):  # knurled cap ridges
        cv2.line(img, (x, z_to_row(148.0)), (x, cap_row), (150, 25, 25), 2)
    cv2.line(img, (0, z_to_row(133.0)), (W, z_to_row(133.0)), (245, 220, 220), 2)
    return img


def _make_bottle() -> tuple[_MeshBuilder, np.ndarray, dict]:
    prof = _bottle_profile_mm()
    seg = np.diff(prof, axis=0)
    seg_len = np.hypot(seg[:, 0], seg[:, 1])
    s = np.concatenate([[0.0], np.cumsum(seg_len)]) / seg_len.sum()
    W = H = 1024

    def z_to_row(z_mm: float) -> int:
        """Texture row of the body at height z (on the straight body or the cap side)."""
        for k in range(len(prof) - 1):
            (r0, z0), (_, z1) = prof[k], prof[k + 1]
            if z1 > z0 and z0 <= z_mm <= z1 and (r0 > 20 or z_mm > 127):
                t = (z_mm - z0) / (z1 - z0)
                return round((1 - (s[k] + t * (s[k + 1] - s[k]))) * H)
        raise ValueError(z_mm)

    albedo = _draw_bottle_label(W, H, z_to_row, np.random.default_rng(7))
    seg_n = np.stack([seg[:, 1], -seg[:, 0]], axis=1) / seg_len[:, None]  # outward (r, z) normals
    # Smooth normals across profile vertices where the profile bends by less than 40 degrees.
    vert_n = []
    for k in range(len(prof)):
        ns = [seg_n[i] for i in (k - 1, k) if 0 <= i < len(seg)]
        smooth = len(ns) == 2 and np.dot(ns[0], ns[1]) > math.cos(math.radians(40))
        vert_n.append(ns[0] + ns[1] if smooth else None)
    z_mid = BOTTLE_HEIGHT_MM / 2
    N = BOTTLE_SEGMENTS
    mesh = _MeshBuilder()

    def corner(k: int, j: float, side: int):
        a = 2 * math.pi * j / N
        r, z = prof[k]
        n2 = vert_n[k] if vert_n[k] is not None else seg_n[k - 1 if side == 0 else k]
        n2 = n2 / np.linalg.norm(n2)
        p = np.array([r * math.cos(a), r * math.sin(a), z - z_mid]) / 1000
        n = np.array([n2[0] * math.cos(a), n2[0] * math.sin(a), n2[1]])
        return mesh.corner(p, (j / N, s[k]), n)

    for k in range(len(prof) - 1):
        for j in range(N):
            a0, a1 = corner(k, j, 1), corner(k, j + 1, 1)
            b0, b1 = corner(k + 1, j, 0), corner(k + 1, j + 1, 0)
            if prof[k][0] == 0:  # bottom pole fan
                mesh.tri(corner(k, j + 0.5, 1), b1, b0)
            elif prof[k + 1][0] == 0:  # top pole fan
                mesh.tri(a0, a1, corner(k + 1, j + 0.5, 0))
            else:
                mesh.tri(a0, a1, b1)
                mesh.tri(a0, b1, b0)
    material = {"roughness": 0.3, "specular": 0.5}
    return mesh, albedo, material


# ---------------------------------------------------------------------------------------------
# Writing a model directory

_MAKERS = {"box": _make_box, "bottle": _make_bottle}


def _models_info(points_m: np.ndarray) -> dict:
    """BOP models_info entry (millimetres) of a model's vertices; no symmetries."""
    p = points_m * 1000
    unique = p[np.unique(np.round(p, 3), axis=0, return_index=True)[1]]
    # The farthest pair are hull vertices: the same maximum, without an all-pairs matrix of a large mesh.
    unique = unique[np.sort(ConvexHull(unique).vertices)]
    d = np.sqrt(((unique[:, None] - unique[None]) ** 2).sum(-1)).max()
    lo, hi = p.min(0), p.max(0)
    info = {"diameter": d}
    info.update({f"min_{a}": lo[i] for i, a in enumerate("xyz")})
    info.update({f"size_{a}": hi[i] - lo[i] for i, a in enumerate("xyz")})
    return {k: round(float(v), 4) + 0.0 for k, v in info.items()}


def _png_bytes(rgb: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 9])
    if not ok:
        raise OSError("could not encode a PNG")
    return buf.tobytes()


def write_object(out: str | Path, name: str, made: tuple[_MeshBuilder, np.ndarray, dict], *,
                 source: str = "n2d_sim.objects", label: str = "sample object", info_extra: dict | None = None,
                 extra: dict | None = None) -> Path:
    """Write a maker's (mesh, albedo, material) as the model directory `out` (files, then the manifest).

    `info_extra` is added to the models_info entry (BOP symmetries), `extra` to the manifest's extra; a material
    "metallic" goes into the MTL as `Pm`.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    mesh, albedo, material = made
    atomic_write_text(out / "mesh.obj", mesh.obj_text(name, label))
    metallic = [f"Pm {material['metallic']:.3f}"] if "metallic" in material else []
    atomic_write_text(out / "mesh.mtl", "\n".join([
        f"# n2d {label} '{name}'", f"newmtl {name}", "Ka 1.000 1.000 1.000", "Kd 1.000 1.000 1.000",
        f"Ks {material['specular']:.3f} {material['specular']:.3f} {material['specular']:.3f}",
        f"Ns {1000 * (1 - material['roughness']) ** 2:.1f}", f"Pr {material['roughness']:.3f}", *metallic,
        "illum 2", "map_Kd albedo.png", ""]))
    atomic_write_bytes(out / "albedo.png", _png_bytes(albedo))
    info = _models_info(mesh.positions()) | (info_extra or {})
    atomic_write_text(out / "models_info.json", json.dumps({"1": info}, indent=2) + "\n")
    config = {"name": name, "material": material}
    extra = {"source": source, "ground_truth": True, "faces": len(mesh.faces),
             "units": "m", "frame": "bounding-box centre, Z up as it stands"} | (extra or {})
    old = read_manifest(out)
    # Keep an equivalent manifest so that regenerating in place changes no byte (it holds a timestamp).
    if old is None or (old["kind"], old.get("complete"), old.get("config"), old.get("extra")) != (
            "model", True, config, extra):
        write_manifest(out, "model", config=config, extra=extra)
    return out


def generate_object(name: str, out_dir: str | Path) -> Path:
    """Write the sample object `name` into `out_dir/<name>/` (files, then the manifest) and return it."""
    if name not in _MAKERS:
        raise ConfigError(f"unknown sample object {name!r}", f"choose one of {', '.join(SAMPLE_OBJECTS)}")
    return write_object(Path(out_dir) / name, name, _MAKERS[name]())


def main(argv: list[str] | None = None) -> None:
    """Regenerate the sample objects: byte-identical files; an equivalent manifest is left as it is."""
    parser = argparse.ArgumentParser(prog="python -m n2d_sim.objects", description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=OBJECTS_DIR, help="parent directory of the object dirs")
    parser.add_argument("names", nargs="*", default=list(SAMPLE_OBJECTS),
                        help="objects to write (default: all)")
    args = parser.parse_args(argv)
    for name in args.names:
        path = generate_object(name, args.out)
        size = sum(f.stat().st_size for f in path.iterdir())
        print(f"{path}: {size / 1024:.0f} KiB")


if __name__ == "__main__":
    main()
