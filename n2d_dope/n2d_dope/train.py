"""Train a DOPE network for one object of an n2d dataset, then export it: the DOPE model directory.

Output (`kind: dope_model`): `checkpoint.pt` (weights, optimiser, position), `model.onnx` (+ `model_int8.onnx`),
`config.json` (what inference needs: object, cuboid keypoints in metres and their order, input convention,
stride, the focal length and image size it was trained at) and `training.json` (losses, timings). While it
trains, the checkpoint lives in `<out>.partial/`: Ctrl-C or a cancel saves it and the same call resumes at the
exact batch (the frame order and augmentation are drawn from (seed, epoch, frame)).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from pathlib import Path

import numpy as np
import torch
from torch.nn.parallel import DistributedDataParallel

from n2d_common.config import to_dict
from n2d_common.contracts import atomic_write_json, discard_on_bad_input, open_stage, stage_output
from n2d_common.errors import Cancelled, ConfigError, ContractError, N2DError
from n2d_common.progress import Eta, Progress, ProgressFn, no_progress
from n2d_common.torch_utils import atomic_torch_save, load_checkpoint, resolve_device
from n2d_dope.config import TrainConfig
from n2d_dope.data import (
    ANY_OBJECT,
    DatasetInfo,
    DopeSamples,
    Frame,
    check_mix,
    epoch_order,
    instances,
    open_datasets,
)
from n2d_dope.distributed import ONE, Ranks, current, launch, shard, share
from n2d_dope.export import export_onnx, quantize_int8
from n2d_dope.network import DopeNet, parameter_count
from n2d_dope.pose_refine import Refiner
from n2d_dope.prior import PRIOR, PRIOR_DIR, prior_weights

INPUT_CONVENTION = "float32 N x 3 x H x W, RGB, 0..1 (normalisation is inside the network), H and W multiples of 16"
_NOT_IDENTITY = ("device", "threads", "checkpoint_every_s", "max_minutes", "int8", "calibration_frames")
"""Config fields that do not change the training itself: a checkpoint written with other values still resumes."""


def select_object(info: DatasetInfo, object_name: str | None, any_object: bool = False) -> str:
    """The object to train for: `object_name`, or the dataset's only object; `ANY_OBJECT` for a generic prior."""
    names = sorted(info.cuboid_points_m)
    if any_object:
        if object_name is not None:
            raise ConfigError(f"any_object trains on every object, but object {object_name!r} was named",
                              "name no object, or set any_object: false")
        return ANY_OBJECT
    if object_name is None:
        if len(names) != 1:
            raise ConfigError(f"{info.directory} shows {len(names)} objects ({', '.join(names)})",
                              "choose one with --object NAME")
        return names[0]
    if object_name not in info.cuboid_points_m:
        raise ConfigError(f"{info.directory} has no object {object_name!r}", f"its objects: {', '.join(names)}")
    return object_name


def split_frames(info: DatasetInfo, object_name: str, cfg: TrainConfig) -> tuple[list[Frame], list[Frame]]:
    """(training, held-out) frames showing the object; every k-th such frame is held out."""
    shown = [f for f in info.frames
             if instances(json.loads(f.annotation.read_text()), object_name, cfg.min_visibility)]
    if len(shown) < 2:
        raise ContractError(f"{info.directory} shows {object_name} in {len(shown)} frame(s)",
                            "generate more frames (n2d dataset --frames N)")
    if cfg.holdout == 0:
        return shown, []
    every = max(2, round(1 / cfg.holdout))
    return ([f for i, f in enumerate(shown) if i % every != every - 1],
            [f for i, f in enumerate(shown) if i % every == every - 1])


def dope_loss(outputs, beliefs: torch.Tensor, affinities: torch.Tensor, peak_weight: float = 0.0) -> torch.Tensor:
    """DOPE's loss: mean squared error of every stage's beliefs and affinities (intermediate supervision).

    `peak_weight` > 0 weighs each belief cell by 1 + peak_weight * its target, so the few cells near a keypoint
    count as much as the many empty ones and the peaks grow early in training (0: DOPE's plain MSE)."""
    out_beliefs, out_affinities = outputs
    weight = 1.0 + peak_weight * beliefs if peak_weight else None
    return sum(((b - beliefs) ** 2 * (weight if weight is not None else 1.0)).mean() + ((a - affinities) ** 2).mean()
               for b, a in zip(out_beliefs, out_affinities))


def learning_rate(cfg: TrainConfig, done: float) -> float:
    """Cosine decay from `cfg.lr` to `cfg.lr_final_fraction * cfg.lr` as the run goes from 0 to 1 done (the larger of
    the fraction of steps and of `max_minutes`, so a time-limited run also ends annealed)."""
    f = cfg.lr_final_fraction
    return cfg.lr * (f + (1 - f) * 0.5 * (1 + math.cos(math.pi * min(1.0, done))))


def _batches(samples: DopeSamples, order: np.ndarray, batch_size: int, start: int, ranks: Ranks = ONE):
    """Yield (index, stacked batch, loss weight) from batch `start` on, loading the next batch in a thread meanwhile;
    with several ranks, this rank's share of each batch and the weight of its loss (`distributed.shard`)."""
    def load(b: int):
        # numpy only in this thread: a torch op here would start a second OpenMP team that fights the
        # training step's for the cores (measured: 3x slower steps on 2 cores)
        mine, weight = shard(list(order[b * batch_size:(b + 1) * batch_size]), ranks)
        items = [samples[int(i)] for i in mine]
        return tuple(np.stack([x.numpy() for x in t]) for t in zip(*items)), weight

    count = math.ceil(len(order) / batch_size)
    with ThreadPoolExecutor(1) as pool:
        pending = pool.submit(load, start) if start < count else None
        for b in range(start, count):
            batch, weight = pending.result()
            pending = pool.submit(load, b + 1) if b + 1 < count else None
            yield b, tuple(torch.from_numpy(x) for x in batch), weight


def memory_format(device: torch.device) -> torch.memory_format:
    """NHWC on the CPU, where oneDNN runs the lite network's training step about twice as fast in it
    (docs/experiments.md); CUDA keeps the default."""
    return torch.channels_last if device.type == "cpu" else torch.contiguous_format


def _identity(cfg: TrainConfig, object_name: str, datasets: list[Path]) -> dict:
    config = {k: v for k, v in to_dict(cfg).items() if k not in _NOT_IDENTITY}
    names = [str(d.absolute()) for d in datasets]
    return {"object": object_name, "dataset": names[0] if len(names) == 1 else names, "train": config}


def initial_weights(cfg: TrainConfig) -> dict | None:
    """The weights of `cfg.init_model` to start from (None without one), checked to fit the configured network."""
    if not cfg.init_model:
        return None
    if cfg.init_model == PRIOR:
        return prior_weights(cfg.backbone, cfg.stages)
    open_stage(cfg.init_model, "dope_model")
    model = json.loads((Path(cfg.init_model) / "config.json").read_text())
    if (model["backbone"], model["stages"]) != (cfg.backbone, cfg.stages):
        raise ConfigError(f"init_model {cfg.init_model} is a {model['backbone']} network with {model['stages']} "
                          f"stages, this training a {cfg.backbone} one with {cfg.stages}",
                          "set the same backbone and stages, or another init_model")
    return load_checkpoint(Path(cfg.init_model) / "checkpoint.pt")["model"]


def train(dataset_dir: str | Path | list[str | Path], out: str | Path, cfg: TrainConfig | None = None, *,
          object_name: str | None = None, overwrite: bool = False, progress: ProgressFn = no_progress,
          cancel: threading.Event | None = None, ddp: int = 0) -> dict | None:
    """Train DOPE for `object_name` on the dataset (or the frames of several, rendered with the same camera) and
    write the DOPE model directory `out`; returns the summary (None on ranks other than 0).

    Raises Cancelled (after saving the checkpoint) when `cancel` is set; the same call resumes. `ddp` > 1 trains
    data-parallel in that many processes of this machine; under torchrun (or in a process group set up by Ray
    Train) every rank calls `train` and takes its share (`distributed.py`).
    """
    cfg = cfg or TrainConfig()
    if ddp > 1:
        return launch(ddp, resolve_device(cfg.device), train, (dataset_dir, out, cfg),
                      {"object_name": object_name, "overwrite": overwrite}, {"progress": progress, "cancel": cancel})
    datasets = [dataset_dir] if isinstance(dataset_dir, (str, Path)) else list(dataset_dir)
    info = open_datasets(datasets)
    initial = initial_weights(cfg)
    name = select_object(info, object_name, cfg.any_object)
    train_frames, held_frames = split_frames(info, name, cfg)
    check_mix(info, train_frames, name, cfg.photoreal_mix)
    device = resolve_device(cfg.device)
    ranks = current(device)
    progress = progress if ranks.main else no_progress  # rank 0 reports for all
    if device.type == "cuda" and ranks.world > 1:
        device = torch.device("cuda", ranks.local)
    if cfg.threads or ranks.world > 1:
        torch.set_num_threads(cfg.threads or max(1, len(os.sched_getaffinity(0)) // ranks.world))
    identity = _identity(cfg, name, [Path(d) for d in datasets])
    stage_cm = stage_output(out, "dope_model", overwrite=overwrite, config=identity) if ranks.main else nullcontext()
    with stage_cm as stage, (discard_on_bad_input(stage, "checkpoint.pt") if ranks.main else nullcontext()):
        ckpt_path = stage.path / "checkpoint.pt" if ranks.main else None
        # rank 0's checkpoint on every rank: the others may run on machines without the output directory
        state = share(load_checkpoint(ckpt_path) if ranks.main and ckpt_path.is_file() else None, ranks)
        torch.manual_seed(cfg.seed)
        fmt = memory_format(device)
        net = DopeNet(cfg.backbone, cfg.stages, imagenet_weights=state is None and initial is None,
                      frozen_blocks=cfg.frozen_blocks).to(device, memory_format=fmt)
        if state is None and initial is not None:
            net.load_state_dict(initial)
        model = DistributedDataParallel(net) if ranks.world > 1 else net  # DDP averages the ranks' gradients
        opt = torch.optim.Adam([p for p in net.parameters() if p.requires_grad], lr=cfg.lr)
        steps_per_epoch = math.ceil(len(train_frames) / cfg.batch_size)
        total = cfg.epochs * steps_per_epoch
        pos = {"step": 0, "elapsed_s": 0.0, "losses": []}
        if state is not None:
            net.load_state_dict(state["model"])
            opt.load_state_dict(state["optimizer"])
            pos = state["position"]

        def save() -> None:
            if not ranks.main:
                return
            atomic_torch_save({"model": net.state_dict(), "optimizer": opt.state_dict(),
                               "position": pos, "identity": identity}, ckpt_path)

        samples = DopeSamples(train_frames, name, cfg, augment=True, symmetric=symmetric_targets(info, name, cfg))
        eta, t_start, last_save = Eta(), time.monotonic() - pos["elapsed_s"], time.monotonic()
        limit_s = cfg.max_minutes * 60 if cfg.max_minutes > 0 else math.inf

        def done(p: dict) -> float:
            """How far the run is: the larger of its steps and its time limit used."""
            return min(1.0, max(p["step"] / total, p["elapsed_s"] / limit_s))

        net.train()
        stopped_early = False
        updating = False
        try:
            while pos["step"] < total and not stopped_early:
                epoch, first = divmod(pos["step"], steps_per_epoch)
                samples.set_epoch(epoch)
                order = epoch_order(train_frames, cfg.photoreal_mix, np.random.default_rng([cfg.seed, epoch]))
                epoch_losses = []
                for _, (images, beliefs, affinities), weight in _batches(samples, order, cfg.batch_size, first, ranks):
                    for group in opt.param_groups:
                        group["lr"] = learning_rate(cfg, done(pos))
                    loss = dope_loss(model(images.to(device, memory_format=fmt)), beliefs.to(device),
                                     affinities.to(device), cfg.peak_weight)
                    if not torch.isfinite(loss):
                        raise N2DError(f"the training loss became {loss.item()} at step {pos['step']}",
                                       "lower --set lr=..., or re-run with --overwrite")
                    opt.zero_grad(set_to_none=True)
                    (loss * weight if ranks.world > 1 else loss).backward()
                    updating = True  # an interrupt until the step is counted leaves the state half stepped
                    opt.step()
                    pos["step"] += 1
                    pos["elapsed_s"] = time.monotonic() - t_start
                    updating = False
                    value = _agree(loss.item() * weight, pos, ranks)
                    epoch_losses.append(value)
                    fraction = done(pos)
                    progress(Progress(0.95 * fraction, "training", eta(fraction),
                                      f"epoch {epoch + 1}/{cfg.epochs} step {pos['step']}/{total} loss {value:.5f}",
                                      {"epoch": epoch + 1, "step": pos["step"], "steps": total, "loss": value}))
                    if _rank0_says(cancel is not None and cancel.is_set(), ranks):
                        save()
                        raise Cancelled(f"training cancelled at step {pos['step']}/{total}",
                                        "re-run the same command to resume")
                    if pos["elapsed_s"] >= limit_s:
                        stopped_early = True
                        break
                    if time.monotonic() - last_save >= cfg.checkpoint_every_s:
                        save()
                        last_save = time.monotonic()
                pos["losses"].append(float(np.mean(epoch_losses)) if epoch_losses else None)
                save()
        except KeyboardInterrupt:  # Ctrl-C (the CLI's SIGINT): keep the steps done since the last checkpoint
            if not updating:
                save()
            raise
        if not ranks.main:
            return None
        net.eval().to(memory_format=torch.contiguous_format)
        summary = _finish(stage.path, net, info, name, train_frames, held_frames, cfg, pos, total, device, progress)
        summary["parameters"] = parameter_count(net)
        summary["processes"] = ranks.world
        atomic_write_json(stage.path / "training.json", summary)
        inputs = {"dataset" if i == 0 else f"dataset_{i + 1}": Path(d) for i, d in enumerate(datasets)}
        if cfg.init_model:
            inputs["init_model"] = PRIOR_DIR if cfg.init_model == PRIOR else Path(cfg.init_model)
        stage.finish(config=identity, inputs=inputs, extra={"object": name,
                                                                                  "backbone": cfg.backbone})
    return summary


def _agree(weighted_loss: float, pos: dict, ranks: Ranks) -> float:
    """After a step, every rank's view of it: the batch's loss (the ranks' weighted losses averaged) and rank 0's
    elapsed time (so the learning rate and a time limit agree on every rank)."""
    if ranks.world == 1:
        return weighted_loss
    stats = torch.tensor([weighted_loss, pos["elapsed_s"] if ranks.main else 0.0], dtype=torch.float64)
    torch.distributed.all_reduce(stats)
    pos["elapsed_s"] = float(stats[1])
    return float(stats[0]) / ranks.world


def _rank0_says(flag: bool, ranks: Ranks) -> bool:
    """Rank 0's `flag` (its cancel) on every rank, so all stop at the same step."""
    if ranks.world == 1:
        return flag
    box = torch.tensor([float(flag and ranks.main)])
    torch.distributed.all_reduce(box)
    return bool(box[0])


def symmetric_targets(info: DatasetInfo, name: str, cfg: TrainConfig) -> dict[str, tuple[np.ndarray, list]]:
    """Object name -> (cuboid keypoints, symmetric poses) of the trained object(s) that have symmetries, when
    training is symmetry-aware (empty otherwise)."""
    if not cfg.symmetry_aware:
        return {}
    return {n: (info.cuboid_points_m[n], poses) for n, poses in info.symmetries.items() if name in (n, ANY_OBJECT)}


def held_out_loss(net: DopeNet, info: DatasetInfo, frames: list[Frame], name: str, cfg: TrainConfig,
                  device: torch.device) -> float | None:
    """Mean DOPE loss of the network on un-augmented held-out frames."""
    if not frames:
        return None
    samples = DopeSamples(frames, name, cfg, augment=False, symmetric=symmetric_targets(info, name, cfg))
    losses = []
    with torch.no_grad():
        for _, (images, beliefs, affinities), _ in _batches(samples, np.arange(len(samples)), cfg.batch_size, 0):
            losses.append(dope_loss(net(images.to(device)), beliefs.to(device), affinities.to(device)).item())
    return float(np.mean(losses))


OBJECT_MODEL = "object"
"""Subdirectory of a DOPE model directory holding a copy of the object's model."""


def _copy_object_model(info: DatasetInfo, name: str, out: Path) -> bool:
    """Copy the object's model (the dataset's copy) into the DOPE directory, so that refinement and tracking have
    it wherever the directory goes; False when the dataset has none."""
    source = info.directory / "models" / name
    if not (source / "mesh.obj").is_file():
        return False
    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(source, out)
    return True


def _finish(directory: Path, net: DopeNet, info: DatasetInfo, name: str, train_frames: list[Frame],
            held_frames: list[Frame], cfg: TrainConfig, pos: dict, total: int, device: torch.device,
            progress: ProgressFn) -> dict:
    """Held-out loss, ONNX (+ INT8) export and config.json; returns the training summary."""
    progress(Progress(0.95, "exporting", -1.0, "held-out loss and ONNX export"))
    held = held_out_loss(net, info, held_frames, name, cfg, device)
    onnx = export_onnx(net, directory / "model.onnx", cfg.input_size, cfg.opset)
    models = {"fp32": "model.onnx"}
    if cfg.int8:
        calib = DopeSamples(train_frames[::max(1, len(train_frames) // cfg.calibration_frames)]
                            [:cfg.calibration_frames], name, cfg, augment=False)
        onnx["int8"] = quantize_int8(directory / "model.onnx", directory / "model_int8.onnx",
                                     [calib[i][0][None].numpy() for i in range(len(calib))])
        models["int8"] = "model_int8.onnx"
    config = {
        "object": name,
        "backbone": cfg.backbone,
        "stages": cfg.stages,
        "models": models,
        "input": INPUT_CONVENTION,
        "input_names": ["image"], "output_names": ["belief", "affinity"],
        "stride": 8,
        "map_cell_centre": "map cell j is centred on input pixel 8 j + 3.5",
        "trained_input_size": list(cfg.input_size),
        "trained_focal_px": info.focal_px * (cfg.zoom if cfg.crop else min(cfg.input_size[0] / info.image_size[0],
                                                                      cfg.input_size[1] / info.image_size[1])),
        "cuboid_order": info.cuboid_order,
        # a generic prior (any_object) has no one cuboid: it is a starting point, not a detector
        "cuboid_points_m": info.cuboid_points_m[name].tolist() if name in info.cuboid_points_m else None,
        "symmetry_aware": bool(symmetric_targets(info, name, cfg)),
        "model_frame": "the n2d model frame (bounding-box centre, Z up as it stood)",
        "pose": "T_cam_obj: object frame -> OpenCV camera frame, metres",
        "model_dir": info.models.get(name, ""),
        "opset": cfg.opset,
    }
    if name != ANY_OBJECT and _copy_object_model(info, name, directory / OBJECT_MODEL):
        progress(Progress(0.98, "exporting", -1.0, "the object's sparse viewpoint model for refinement"))
        Refiner(directory / OBJECT_MODEL, cache_dir=directory)
        config["object_model"] = OBJECT_MODEL
    atomic_write_json(directory / "config.json", config)
    progress(Progress(1.0, "done", 0.0, f"{pos['step']} steps"))
    return {"object": name, "backbone": cfg.backbone, "steps": pos["step"], "planned_steps": total,
            "stopped_at_time_limit": pos["step"] < total, "train_frames": len(train_frames),
            "held_out_frames": len(held_frames), "epoch_losses": pos["losses"], "held_out_loss": held,
            "train_seconds": round(pos["elapsed_s"], 1), "device": str(device), "export": onnx}
