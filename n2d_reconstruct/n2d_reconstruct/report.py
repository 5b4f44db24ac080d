"""The model's quality report: held-out image metrics, geometry against a ground truth, and preview.png.

Image metrics compare each held-out photo with a render from the same camera, over the pixels of
the photo's object mask, both black outside it (the background is not modelled): the textured mesh
(`mesh_*`) and, when the method has them, the radiance field (`field_*`) and the stage 2 model (`stage2_*`).
PSNR in dB, SSIM (Gaussian, sigma 1.5), FLIP (lower is better); simulated sessions are also scored against their
noise-free images (`clean_*`). Against a ground truth: Chamfer distance (mean of both directions) and F-score at
`fscore_threshold_m`, with the ground-truth mesh placed in the turntable frame, and the albedo against the true
one (`albedo_psnr_db`).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import trimesh

from n2d_common.formats.model import diameter, read_textured_model
from n2d_common.frames import inv_T, make_T, transform_points
from n2d_common.images import contact_sheet, write_png
from n2d_common.raster import rasterize, render_textured
from n2d_reconstruct.data import Views
from n2d_reconstruct.metrics import flip, mesh_distances, psnr, ssim
from n2d_reconstruct.texture import TexturedMesh

FieldRender = Callable[[np.ndarray, np.ndarray, int, int, np.ndarray], np.ndarray]
"""(K, T_turntable_cam, width, height, pixel mask) -> H x W x 3 float image in [0, 1]."""
PREVIEW_VIEWS = 3
"""Held-out views shown in preview.png."""


def ground_truth_mesh(model_dir: Path) -> trimesh.Trimesh:
    """A ground-truth model placed as the simulator places it: model origin over the plate centre, its lowest
    point on the plate (the turntable frame of a session whose first view is at plate angle 0)."""
    mesh = trimesh.load(Path(model_dir) / "mesh.obj", force="mesh")
    return mesh.apply_transform(make_T(np.eye(3), [0.0, 0.0, -mesh.vertices[:, 2].min()]))


def image_metrics(views: Views, tm: TexturedMesh, renders: dict[str, FieldRender] | None = None
                  ) -> tuple[dict, list]:
    """Mean held-out metrics of the textured mesh (and of other renderers: the NeuS field, the stage 2 model) in
    the turntable frame, and one row of preview images (photo, mesh, the renderers', shaded geometry) per view.

    Keys `{mesh,<renderer>}_{psnr_db,ssim,flip}` score the renders against the photos. When the views have
    noise-free images (a simulated session), `clean_{mesh,field}_*` score them against those, and
    `clean_photo_*` scores the photo itself: what a perfect model would get against the photos.
    """
    scores: dict[str, list[float]] = {}
    rows = []
    for i in range(len(views)):
        T_cam = inv_T(views.T_turntable_cam[i])
        photo, mask = views.rgb[i], views.masks[i]
        rendered, _ = render_textured(tm.vertices, tm.faces, tm.face_uvs, tm.albedo, views.K, T_cam,
                                      views.width, views.height)
        images = {"mesh": rendered}
        for name, render in (renders or {}).items():
            images[name] = np.clip(np.rint(255 * render(views.K, views.T_turntable_cam[i], views.width,
                                                        views.height, mask)), 0, 255).astype(np.uint8)
        pairs = [(name, photo, image) for name, image in images.items()]
        if views.truth is not None:
            clean = views.truth[i]
            pairs += [(f"clean_{name}", clean, image) for name, image in images.items()]
            pairs.append(("clean_photo", clean, photo))
        for name, reference, image in pairs:
            for metric, value in _scores(reference, image, mask).items():
                scores.setdefault(f"{name}_{metric}", []).append(value)
        rows.append([photo, *images.values(), shaded(tm, views.K, T_cam, views.width, views.height)])
    means = {k: round(float(np.mean(v)), 4) for k, v in scores.items()}
    return means | {"heldout_views": len(views)}, rows


def _scores(reference: np.ndarray, image: np.ndarray, mask: np.ndarray) -> dict[str, float]:
    """PSNR, SSIM and FLIP over the object mask, both images black outside it (the background is not
    modelled, so SSIM windows at the outline compare the object against the same black)."""
    reference, image = reference * mask[..., None], image * mask[..., None]
    return {"psnr_db": psnr(reference, image, mask), "ssim": ssim(reference, image, mask),
            "flip": flip(reference, image, mask)}


UNDERSIDE_FRACTION = 0.1
"""The underside, measured on its own: the surface within this fraction of the true height of the plate."""


def albedo_metrics(views: Views, tm: TexturedMesh, truth_dir: Path) -> dict:
    """The albedo against the simulator's true one: both textured meshes rendered unlit in the views (the truth
    placed as `ground_truth_mesh` places it), PSNR over the pixels both cover after a least-squares gain per colour
    channel (a baked albedo carries the capture's exposure and shading; a highlight baked into it stays an error)."""
    vertices, faces, face_uvs, albedo = read_textured_model(Path(truth_dir))
    vertices = vertices - [0.0, 0.0, vertices[:, 2].min()]
    scores = []
    for i in range(len(views)):
        T_cam = inv_T(views.T_turntable_cam[i])
        true, true_mask = render_textured(vertices, faces, face_uvs, albedo, views.K, T_cam, views.width, views.height)
        ours, our_mask = render_textured(tm.vertices, tm.faces, tm.face_uvs, tm.albedo, views.K, T_cam, views.width,
                                         views.height)
        both = true_mask & our_mask
        if not both.any():
            continue
        a, b = ours[both].astype(np.float64), true[both].astype(np.float64)
        gain = (a * b).sum(0) / np.maximum((a * a).sum(0), 1e-9)
        mse = float(np.mean((np.clip(a * gain, 0, 255) - b) ** 2)) / 255.0 ** 2
        scores.append(10 * np.log10(1.0 / max(mse, 1e-12)))
    return {"albedo_psnr_db": round(float(np.mean(scores)), 4) if scores else None}


def geometry_metrics(mesh: trimesh.Trimesh, truth: trimesh.Trimesh, threshold_m: float) -> dict:
    """Chamfer, F-score and bounding-box size error of `mesh` against `truth` (both in the turntable frame), and
    the Chamfer of the underside alone (what a one-placement capture never sees)."""
    d = mesh_distances(mesh.vertices, mesh.faces, truth.vertices, truth.faces, threshold=threshold_m)
    lo, hi = truth.vertices[:, 2].min(), truth.vertices[:, 2].max()
    under = mesh_distances(mesh.vertices, mesh.faces, truth.vertices, truth.faces, n=50_000, threshold=threshold_m,
                           below_z=lo + UNDERSIDE_FRACTION * (hi - lo))
    size, true_size = np.ptp(mesh.vertices, axis=0), np.ptp(truth.vertices, axis=0)
    return {"chamfer_mm": round(1000 * d["chamfer"], 3),
            "chamfer_pct_diameter": round(100 * d["chamfer"] / diameter(truth.vertices), 3),
            "accuracy_mm": round(1000 * d["a_to_b"], 3), "completeness_mm": round(1000 * d["b_to_a"], 3),
            "fscore": round(d["fscore"], 4), "fscore_threshold_mm": 1000 * threshold_m,
            "underside_chamfer_mm": round(1000 * under["chamfer"], 3),
            "underside_completeness_mm": round(1000 * under["b_to_a"], 3),
            "bbox_size_error_pct": [round(float(x), 3) for x in 100 * (size - true_size) / true_size]}


def shaded(tm: TexturedMesh, K: np.ndarray, T_cam: np.ndarray, width: int, height: int) -> np.ndarray:
    """H x W x 3 uint8 grey render of the geometry alone, lit from the camera (face normals)."""
    cam = transform_points(T_cam, tm.vertices)
    r = rasterize(cam, tm.faces, K, width, height)
    normals = trimesh.Trimesh(cam, tm.faces, process=False).face_normals
    out = np.zeros((height, width, 3), np.uint8)
    light = np.abs(normals[r.face[r.mask], 2])
    out[r.mask] = (40 + 200 * light)[:, None].astype(np.uint8)
    return out


def write_preview(path: Path, rows: list[list[np.ndarray]], labels: list[str]) -> None:
    """preview.png: the first PREVIEW_VIEWS rows of (photo, renders..., geometry), cropped to the object."""
    rows = rows[:PREVIEW_VIEWS]
    drawn = np.any([im.any(-1) for row in rows for im in row[1:]], axis=0)
    ys, xs = np.nonzero(drawn)
    if len(xs):
        pad = 20
        y0, y1 = max(0, ys.min() - pad), min(drawn.shape[0], ys.max() + pad)
        x0, x1 = max(0, xs.min() - pad), min(drawn.shape[1], xs.max() + pad)
        rows = [[im[y0:y1, x0:x1] for im in row] for row in rows]
    write_png(path, contact_sheet([im for row in rows for im in row], labels * len(rows), cols=len(labels),
                                  thumb_width=320))
