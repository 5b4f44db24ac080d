"""The dataset stage: model directories -> a rendered, annotated dataset directory (BOP + DOPE).

Frames are split across `workers` render processes (frame i goes to worker i mod K); each writes its
frames straight into `<out>.partial`. With `cluster`, Ray actors on the cluster's nodes render them instead and
send each frame's files back to be written there (`cluster.py`): the same frames, the same records.
Progress, ETA and cancel cover all workers. A run that stops (Ctrl-C, cancel, crash) keeps every finished
frame; the same command resumes with the missing ones.
At the end the per-frame records become BOP's chunk files, the models and camera.json are written,
a contact sheet is drawn from the written annotations, and the directory is published complete.
"""

from __future__ import annotations

import threading
import time
from contextlib import ExitStack
from pathlib import Path

from n2d_common.cluster import connect
from n2d_common.config import to_dict
from n2d_common.contracts import stage_output
from n2d_common.errors import Cancelled, N2DError
from n2d_common.progress import Eta, Progress, ProgressFn, no_progress
from n2d_common.worker import run_in_worker
from n2d_dataset import writer
from n2d_dataset.config import DatasetConfig
from n2d_dataset.models import CUBOID_ORDER, CUBOID_SIGNS, load_models
from n2d_dataset.sheet import write_contact_sheet


def _render(**kwargs) -> dict:
    # Imported here, in the worker process only: bpy must never be imported into the caller's process
    # (it holds global state, and a spawned child would inherit the sys.path entries it adds).
    if kwargs.pop("engine") == "raster":
        from n2d_dataset.raster_worker import render_frames
    else:
        from n2d_dataset.render_worker import render_frames

    return render_frames(**kwargs)


def _job_config(cfg: DatasetConfig) -> dict:
    """The config that identifies a job (the worker count does not change what is rendered)."""
    data = to_dict(cfg)
    data.pop("workers")
    return data


def _render_local(job: dict, engine: str, frames: list[int], cfg: DatasetConfig, report: ProgressFn,
                  cancel: threading.Event) -> None:
    """Render `frames` with `engine` in local worker processes (the k-th of K workers takes every K-th frame)."""
    errors = []

    def work(shard: list[int]) -> None:
        try:
            run_in_worker(_render, job | {"frames": shard, "engine": engine}, progress=report, cancel=cancel)
        except N2DError as exc:
            errors.append(exc)
            cancel.set()  # one worker failing stops the others; their frames are kept

    workers = cfg.worker_count(engine)
    threads = [threading.Thread(target=work, args=(frames[k::workers],), daemon=True) for k in range(workers)
               if frames[k::workers]]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if errors:
        cancelled = [e for e in errors if isinstance(e, Cancelled)]
        raise (errors[0] if len(cancelled) < len(errors) else Cancelled(
            f"cancelled with {len(writer.done_frames(Path(job['root'])))} of {cfg.frames} frames done",
            "re-run the same command to resume"))


def generate_dataset(model_dirs: list[str | Path], out: str | Path, cfg: DatasetConfig, *, overwrite: bool = False,
                     progress: ProgressFn = no_progress, cancel: threading.Event | None = None,
                     cluster: str | None = None) -> dict:
    """Render `cfg.frames` annotated frames of the models into the dataset directory `out`; returns a summary.

    `cluster`: render on a Ray cluster instead of local worker processes (`ray://HOST:PORT`, `HOST:PORT`, `auto`
    or `local`, see `n2d_common.cluster`); the same frames, written into `out` on this machine."""
    models = load_models(model_dirs)
    cancel = cancel or threading.Event()
    out = Path(out).absolute()
    t_start = time.perf_counter()
    job = _job_config(cfg) | {"models": [str(m.directory) for m in models]}
    with ExitStack() as stack:
        # the cluster first: an unreachable one leaves not even a partial directory
        ray = stack.enter_context(connect(cluster)) if cluster else None
        stage = stack.enter_context(stage_output(out, "dataset", overwrite=overwrite, config=job))
        root = stage.path
        todo = sorted(set(range(cfg.frames)) - writer.done_frames(root))
        done = cfg.frames - len(todo)
        eta, lock = Eta(), threading.Lock()
        counts = {"done": done}

        def report(_p: Progress) -> None:
            with lock:
                counts["done"] += 1
                f = counts["done"] / cfg.frames
                progress(Progress(f, "rendering", eta(f), f"{counts['done']}/{cfg.frames} frames",
                                  {"frames_done": counts["done"], "frames_total": cfg.frames}))

        progress(Progress(done / cfg.frames, "rendering", -1.0, f"{done}/{cfg.frames} frames (resumed)" if done else
                          "starting render workers", {"frames_done": done, "frames_total": cfg.frames}))
        photoreal = set(cfg.photoreal())
        work = {"model_dirs": [str(m.directory) for m in models], "root": str(root), "config": to_dict(cfg)}
        # One engine at a time: a Cycles worker already uses every core.
        for engine, frames in (("cycles", [f for f in todo if f in photoreal]),
                               ("raster", [f for f in todo if f not in photoreal])):
            if not frames:
                continue
            if ray is not None:
                from n2d_dataset.cluster import render_on_cluster

                render_on_cluster(ray, work, engine, frames, cfg, report, cancel)
            else:
                _render_local(work, engine, frames, cfg, report, cancel)
        missing = sorted(set(range(cfg.frames)) - writer.done_frames(root))
        if missing:  # never publish a dataset with holes
            raise N2DError(f"{len(missing)} of {cfg.frames} frames are missing (first: {missing[0]})",
                           "re-run the same command to render them")
        progress(Progress(1.0, "writing", 0.0, "chunk files, models, contact sheet",
                          {"frames_done": cfg.frames, "frames_total": cfg.frames}))
        totals = writer.assemble(root, cfg.frames, cfg.chunk_size)
        writer.write_models(root, models)
        writer.write_camera(root, cfg.camera.K(), cfg.camera.width, cfg.camera.height)
        if cfg.annotate:
            writer.write_ndds_settings(root, models, cfg.camera.K(), cfg.camera.width, cfg.camera.height)
        if cfg.annotate:
            write_contact_sheet(root, cfg.frames, cfg.chunk_size, cfg.render.rgb_format, seed=cfg.seed)
        summary = {"frames": cfg.frames, "instances": totals["instances"], "resumed_frames": done,
                   "wall_s": round(time.perf_counter() - t_start, 2), "phase_seconds": totals["seconds"],
                   "worker_rss_mb": totals["worker_rss_mb"],
                   "models": {m.name: m.obj_id for m in models}, "cluster": cluster or None}
        stage.finish(config=to_dict(cfg), inputs={m.name: m.directory for m in models}, extra={
            "layout": "BOP train_pbr chunks; DOPE JSON next to each rgb image",
            "units": {"bop": "mm", "dope": "cm", "depth_scale_mm": writer.DEPTH_SCALE},
            "camera_frame": "OpenCV (x right, y down, z forward)",
            "cuboid_order": list(CUBOID_ORDER),
            "cuboid_signs": CUBOID_SIGNS.astype(int).tolist(),
            "cuboids_m": {m.name: {"center": (m.min_m + m.size_m / 2).tolist(), "size": m.size_m.tolist()}
                          for m in models},
            "annotated": cfg.annotate, "renderer": cfg.render.engine, "photoreal_frames": len(cfg.photoreal()),
            **summary})
    return summary
