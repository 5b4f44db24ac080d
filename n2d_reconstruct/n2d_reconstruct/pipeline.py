"""The reconstruction stage: capture session -> model directory (textured metric mesh + report).

Phases: load (checks) -> geometry (the visual hull field; `neus` trains a NeuS field initialised
from it) -> mesh (narrow-band marching cubes, clean-up) -> refine (`fast`: photo-consistency) ->
fair (`neus`: plain surfaces spanned by a membrane) -> stage2 (optional: vertices and a diffuse +
specular appearance fitted by differentiable rendering; the albedo is then baked without highlights) ->
hull (what stands outside the visual hull is pulled back) -> denoise (bilateral normal filtering: ripples
flattened, edges kept) -> planes (broad planar regions made flat, their edges and corners sharp) -> texture (xatlas;
baked from the photos, or from the NeuS colour field) -> export (object frame, OBJ/GLB,
models_info.json) -> report (held-out metrics, geometry against a ground truth, preview).
The output is built in `<out>.partial` and appears complete or not at all; a NeuS run that stops
keeps its checkpoint there and the next run with the same config resumes from it.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

import numpy as np

from n2d_common.config import to_dict
from n2d_common.contracts import atomic_write_json, stage_output
from n2d_common.errors import Cancelled
from n2d_common.frames import inv_T
from n2d_common.progress import Eta, Progress, ProgressFn, no_progress
from n2d_common.symmetry import AmbiguousSymmetry, Symmetries, find_symmetries, to_models_info
from n2d_reconstruct.data import load_session
from n2d_reconstruct.denoise import DenoiseConfig, denoise
from n2d_reconstruct.export import object_frame, write_model
from n2d_reconstruct.fair import FairConfig, fair_plain
from n2d_reconstruct.hull import HullConfig, VisualHull, pull_inside, search_box
from n2d_reconstruct.mesh import MeshConfig, clean, extract_mesh, locate
from n2d_reconstruct.neus import NeusConfig, NeusField, train_neus
from n2d_reconstruct.placements import PlacementsConfig, fuse, register
from n2d_reconstruct.planes import PlanesConfig, flatten_planes
from n2d_reconstruct.refine import RefineConfig, refine_surface
from n2d_reconstruct.report import albedo_metrics, geometry_metrics, ground_truth_mesh, image_metrics, write_preview
from n2d_reconstruct.stage2 import Stage2Config, Stage2Result, refine_stage2
from n2d_reconstruct.texture import TextureConfig, TexturedMesh, bake_from_function, bake_from_views, unwrap

PHASES = {"fast": {"load": 0.02, "geometry": 0.03, "mesh": 0.1, "refine": 0.25, "stage2": 0.05, "hull": 0.01,
                   "denoise": 0.07, "planes": 0.02, "texture": 0.24, "symmetry": 0.01, "export": 0.05, "report": 0.15},
          "neus": {"load": 0.01, "geometry": 0.82, "mesh": 0.03, "fair": 0.01, "stage2": 0.01, "hull": 0.005,
                   "denoise": 0.005, "planes": 0.005, "texture": 0.04, "symmetry": 0.005, "export": 0.01,
                   "report": 0.05}}
"""Share of the progress bar of each phase, per method."""
AABB_MARGIN_M = 0.01
"""NeuS samples inside the visual hull's bounding box grown by this, metres (the hull contains the object)."""


@dataclass
class ReconstructConfig:
    """Capture session to model."""

    method: Literal["fast", "neus"] = "fast"
    """fast: visual hull from the masks refined by photo-consistency, textured from the photos (CPU, minutes);
    neus: a NeuS hash-grid SDF trained from the hull (CUDA when present; see neus.*), textured from its colour
    field."""
    object_name: str = "object"
    """Name of the object (written into the model files and the manifest)."""
    holdout_every: int = 8
    """Every n-th view is held out of reconstruction and used to measure it (0: none)."""
    symmetry: Literal["auto", "none"] = "auto"
    """auto: detect the model's symmetries (rotations mapping its shape and texture onto itself) and write them in
    models_info.json, as BOP does; a model whose symmetry cannot be decided stops the reconstruction with a clear
    error before anything is written. none: write no symmetries (the model is treated as asymmetric)."""
    min_views: int = 8
    """Sessions with fewer views are refused."""
    fscore_threshold_m: float = 0.001
    """Distance under which a point counts as correct in the F-score against a ground truth, metres."""
    hull: HullConfig = field(default_factory=HullConfig)
    """Visual hull."""
    placements: PlacementsConfig = field(default_factory=PlacementsConfig)
    """Registration of the placements of a session where the object was turned over and swept again."""
    mesh: MeshConfig = field(default_factory=MeshConfig)
    """Marching cubes and clean-up."""
    refine: RefineConfig = field(default_factory=RefineConfig)
    """Photo-consistency refinement of the hull."""
    fair: FairConfig = field(default_factory=FairConfig)
    """The membrane over surfaces that show no texture (NeuS)."""
    stage2: Stage2Config = field(default_factory=Stage2Config)
    """Vertex offsets and a diffuse + specular appearance fitted by differentiable rendering (both methods)."""
    denoise: DenoiseConfig = field(default_factory=DenoiseConfig)
    """Feature-preserving denoising of the mesh (both methods)."""
    planes: PlanesConfig = field(default_factory=PlanesConfig)
    """Flattening of planar regions (both methods)."""
    texture: TextureConfig = field(default_factory=TextureConfig)
    """UV atlas and albedo."""
    neus: NeusConfig = field(default_factory=lambda: NeusConfig.preset("cpu"))
    """NeuS training (method neus); the default is the "cpu" preset (`n2d reconstruct --neus-preset gpu`)."""

    def __post_init__(self):
        if self.holdout_every < 0 or self.holdout_every == 1:
            raise ValueError("holdout_every must be 0 (none) or >= 2")
        if self.min_views < 3:
            raise ValueError("min_views must be >= 3")


def _symmetries(tm: TexturedMesh, cfg: ReconstructConfig, progress=None) -> Symmetries:
    """The symmetries of the textured model in its object frame (none when cfg.symmetry is none)."""
    if cfg.symmetry == "none":
        return Symmetries([], [])
    try:
        return find_symmetries(tm.vertices, tm.faces, face_uvs=tm.uvs[tm.faces], texture=tm.albedo)
    except AmbiguousSymmetry as exc:  # the hint of a reconstruction: there is no model to edit yet
        raise AmbiguousSymmetry(exc.message, "reconstruct with --set symmetry=none (no symmetries written), then "
                                "write them into the model's models_info.json by hand (BOP's symmetries_discrete / "
                                "symmetries_continuous)", exc.residual) from None


class _Phases:
    """Progress across the phases, and their wall times."""

    def __init__(self, method: str, progress: ProgressFn, cancel: threading.Event | None):
        self.shares, self.progress, self.cancel = PHASES[method], progress, cancel
        self.done, self.times, self.eta = 0.0, {}, Eta()

    def run(self, name: str, fn, *args, **kwargs):
        if self.cancel is not None and self.cancel.is_set():
            raise Cancelled(f"reconstruction cancelled before the {name} phase", "re-run the same command to resume")
        share, start = self.shares[name], time.monotonic()

        def sub(p: Progress) -> None:
            fraction = self.done + share * p.fraction
            eta = p.eta_s if p.eta_s >= 0 else self.eta(fraction)
            self.progress(Progress(fraction, name, eta, p.message, p.info))

        self.progress(Progress(self.done, name))
        result = fn(*args, progress=sub, **kwargs)
        self.times[name] = round(time.monotonic() - start, 2)
        self.done += share
        return result


def _load(session_dir, cfg: ReconstructConfig, progress: ProgressFn):
    """The session; one of several placements registered (refused when its views disagree) and fused into the
    first placement's frame."""
    data = load_session(session_dir, holdout_every=cfg.holdout_every, min_views=cfg.min_views)
    if data.train.placements < 2:
        return data
    progress(Progress(0.5, "load", message=f"registering {data.train.placements} placements"))
    registration = register(data.train, data.plate_radius_m, cfg.placements, cfg.hull, cfg.mesh.locate_voxel_m)
    return fuse(data, registration)


def _geometry(data, cfg: ReconstructConfig, workdir: Path, cancel, progress: ProgressFn):
    """The visual hull, the SDF to mesh (the forgiving hull on the fast path) and the NeuS field (None on the fast
    path)."""
    hull = VisualHull(data.train, cfg.hull, data.plates)
    if cfg.method == "fast":
        return hull, _forgiving(hull, cfg.hull), None
    box = locate(hull, search_box(data.plate_radius_m, cfg.hull), cfg.mesh.locate_voxel_m)
    aabb = box + [[-AABB_MARGIN_M] * 3, [AABB_MARGIN_M] * 3]
    aabb[0, 2] = max(aabb[0, 2], cfg.hull.plate_clearance_m - cfg.mesh.voxel_m)
    field = train_neus(data.train, aabb, cfg.neus, workdir=workdir, init_sdf=hull, progress=progress, cancel=cancel)
    # The field is meshed inside the (forgiving) hull grown by its slack, and above every plate: the object lies
    # there, and what NeuS puts elsewhere in its box (floaters where few rays pass) is not the object.
    outer, slack = _forgiving(hull, cfg.hull), max(cfg.hull.slack_px, 0.0) * hull.pixel_m
    return hull, (lambda p: np.maximum(np.maximum(field.sdf(p), outer(p) - slack), hull.below_plates(p))), field


def _meshing(cfg: ReconstructConfig) -> MeshConfig:
    """The mesh settings of extraction: the fast path keeps up to `refine.min_faces` faces (or the user's larger
    `mesh.target_faces`) for the refinement, which decimates to `mesh.target_faces` when it is done."""
    if cfg.method != "fast" or not cfg.refine.enabled or not cfg.mesh.target_faces:
        return cfg.mesh
    return replace(cfg.mesh, target_faces=max(cfg.mesh.target_faces, cfg.refine.min_faces))


def _refine(mesh, views, cfg: ReconstructConfig, progress: ProgressFn):
    if not cfg.refine.enabled:
        return mesh, None
    passes = []
    fine = replace(_meshing(cfg), smooth_iterations=cfg.refine.smooth_iterations)
    for i in range(cfg.refine.passes):
        def sub(p: Progress, i=i) -> None:
            progress(replace(p, fraction=(i + p.fraction) / cfg.refine.passes))

        mesh, stats = refine_surface(mesh, views, cfg.refine, sub, fixed=_on_plate(mesh, cfg))
        mesh = clean(mesh, fine)
        passes.append(stats)
    if cfg.mesh.target_faces and len(mesh.faces) > cfg.mesh.target_faces:
        mesh = clean(mesh, replace(cfg.mesh, smooth_iterations=0))
    return mesh, passes[-1] | {"passes": passes}


def _stage2(mesh, views, cfg: ReconstructConfig, progress: ProgressFn):
    if not cfg.stage2.enabled:
        return mesh, None, None
    return refine_stage2(mesh, views, cfg.stage2, progress, fixed=_on_plate(mesh, cfg))


def _forgiving(hull: VisualHull, cfg: HullConfig):
    """The hull's field forgiving the one view whose mask alone notches it (`HullConfig.pull_forgive_px`)."""
    notch = cfg.pull_forgive_px * hull.pixel_m
    return hull if notch < 0 else (lambda points: hull.lenient(points, notch))


def _pull_inside(mesh, hull: VisualHull, cfg: HullConfig, progress: ProgressFn):
    if cfg.slack_px < 0:
        return mesh, None
    return pull_inside(mesh, _forgiving(hull, cfg), cfg.slack_px * hull.pixel_m)


def _on_plate(mesh, cfg: ReconstructConfig) -> np.ndarray:
    """Vertices of the cut on the plate (exact: they stay)."""
    return (mesh.vertices[:, 2] <= cfg.hull.plate_clearance_m + cfg.mesh.voxel_m) & (mesh.vertex_normals[:, 2] < -0.5)


def _texture(mesh, views, cfg: TextureConfig, neus: NeusField | None, staged: Stage2Result | None,
             progress: ProgressFn):
    progress(Progress(0.0, "texture", message="unwrapping (xatlas)"))
    tm = unwrap(mesh, cfg)
    if neus is not None:  # the colour field seen from the most frontal training cameras, weighted like photos
        eyes = views.T_turntable_cam[:, :3, 3]
        tm.albedo = bake_from_function(tm, lambda p, n: neus.albedo(p, n, eyes, sharpness=cfg.sharpness,
                                                                     min_cos=cfg.min_cos), cfg.size_px)
        return tm
    if staged is not None:  # the photos less the highlights stage 2 fitted: an albedo without them
        views = staged.diffuse_views(views)
    tm.albedo = bake_from_views(tm, views, cfg, progress=lambda p: progress(Progress(0.5 + 0.5 * p.fraction, "texture",
                                                                                     message=p.message)))
    return tm


def reconstruct(session_dir: str | Path, out: str | Path, cfg: ReconstructConfig, *,
                ground_truth: str | Path | None = None, overwrite: bool = False,
                progress: ProgressFn = no_progress, cancel: threading.Event | None = None) -> dict:
    """Reconstruct the capture session `session_dir` into the model directory `out`; returns the report.

    `ground_truth`: a model directory of the true object (the simulator's), placed as the simulator
    places it, to measure the geometry. Raises ContractError for bad input, Cancelled on `cancel`.
    """
    phases = _Phases(cfg.method, progress, cancel)
    session_dir = Path(session_dir)
    data = phases.run("load", _load, session_dir, cfg)  # bad input fails before anything is written
    with stage_output(out, "model", overwrite=overwrite, config=to_dict(cfg)) as writer:
        hull, sdf, neus = phases.run("geometry", _geometry, data, cfg, writer.path, cancel)
        mesh = phases.run("mesh", extract_mesh, sdf, search_box(data.plate_radius_m, cfg.hull), _meshing(cfg))
        refined = faired = None
        if cfg.method == "fast":
            mesh, refined = phases.run("refine", _refine, mesh, data.train, cfg)
        else:
            mesh, faired = phases.run("fair", fair_plain, mesh, data.train, cfg.fair, _on_plate(mesh, cfg))
        mesh, staged, staged_stats = phases.run("stage2", _stage2, mesh, data.train, cfg)
        mesh, pulled = phases.run("hull", _pull_inside, mesh, hull, cfg.hull)
        mesh = phases.run("denoise", denoise, mesh, cfg.denoise, _on_plate(mesh, cfg))
        mesh, flattened = phases.run("planes", flatten_planes, mesh, data.train.pixel_m, cfg.planes,
                                     _on_plate(mesh, cfg))
        tm = phases.run("texture", _texture, mesh, data.train, cfg.texture, neus, staged)
        T_turntable_obj = object_frame(tm.vertices)
        model = tm.transformed(inv_T(T_turntable_obj))  # the object frame; tm stays in the turntable frame
        symmetries = phases.run("symmetry", _symmetries, model, cfg)
        info = phases.run("export", lambda progress: write_model(writer.path, model, cfg.object_name,
                                                                 to_models_info(symmetries)))
        report = phases.run("report", _report, writer.path, data, tm, mesh, neus, staged, ground_truth, cfg)
        report["placements"] = data.registration
        report["refine"] = refined
        report["fair"] = faired
        report["stage2"] = staged_stats
        report["hull"] = pulled
        report["planes"] = flattened
        report["symmetry"] = {"mode": cfg.symmetry,
                              "group_order": None if symmetries.continuous else symmetries.group_order,
                              "discrete": len(symmetries.discrete), "continuous": len(symmetries.continuous)}
        report["timings_s"] = phases.times | {"total": round(sum(phases.times.values()), 2)}
        report["model"] = {"faces": len(tm.faces), "vertices": len(tm.vertices), "watertight": mesh.is_watertight,
                           "diameter_mm": info["diameter"],
                           "size_mm": [info["size_x"], info["size_y"], info["size_z"]]}
        atomic_write_json(writer.path / "report.json", report)
        writer.finish(config=to_dict(cfg), inputs={"session": str(session_dir.absolute())},
                      extra={"object": cfg.object_name, "method": cfg.method,
                             "placements": data.train.placements,
                             "T_turntable_obj": np.round(T_turntable_obj, 9).tolist(),
                             "frame": "object frame at the bounding-box centre, axes of the session's turntable "
                                      "frame (Z up); T_turntable_obj maps it into the turntable frame, metres"})
        progress(Progress(1.0, "done"))
        return report


def _report(directory: Path, data, tm, mesh, neus, staged, ground_truth, cfg: ReconstructConfig,
            progress: ProgressFn) -> dict:
    report: dict = {"method": cfg.method, "views": {"train": len(data.train), "heldout": len(data.heldout)}}
    # Without held-out views the preview shows training views, and no image metrics are reported.
    shown = data.heldout if len(data.heldout) else data.train.subset(list(range(min(3, len(data.train)))))
    renders = ({"field": neus.render} if neus is not None else {}) | \
        ({"stage2": staged.render} if staged is not None else {})
    metrics, rows = image_metrics(shown, tm, renders)
    report["heldout"] = metrics if len(data.heldout) else None
    label = "photo (held out)" if len(data.heldout) else "photo (training)"
    labels = [label, "textured mesh"] + (["radiance field"] if neus is not None else []) + \
        (["stage 2 model"] if staged is not None else []) + ["geometry"]
    write_preview(directory / "preview.png", rows, labels)
    if ground_truth is not None:
        report["geometry"] = geometry_metrics(mesh, ground_truth_mesh(Path(ground_truth)), cfg.fscore_threshold_m)
        if len(data.heldout):
            report["geometry"] |= albedo_metrics(data.heldout, tm, Path(ground_truth))
    return report
