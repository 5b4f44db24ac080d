"""Data-parallel DOPE training (torch.distributed, gloo on the CPU): two processes follow the single process's loss
curve, write the same kind of model directory, and resume from their checkpoint."""

import threading

import pytest

from n2d_common.config import load_config
from n2d_common.contracts import read_manifest
from n2d_common.errors import Cancelled
from n2d_common.torch_utils import load_checkpoint
from n2d_dataset.config import DatasetConfig
from n2d_dataset.generate import generate_dataset
from n2d_dope.config import TrainConfig
from n2d_dope.distributed import ONE, Ranks, shard
from n2d_dope.train import train
from n2d_sim.objects import sample_object_dir

SMALL = ["frames=8", "camera.width=320", "camera.height=240", "camera.focal_px=300", "render.engine=raster",
         "scene.distractors=[1,2]", "scene.boards=0", "workers=1"]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("ddp") / "ds"
    generate_dataset([sample_object_dir("box")], out, load_config(DatasetConfig, overrides=SMALL))
    (out / "models" / "box" / "mesh.obj").unlink()  # no refinement model after training: not what this tests (10 s)
    return out


def tiny() -> TrainConfig:
    cfg = TrainConfig.preset("tiny")
    cfg.epochs, cfg.holdout, cfg.int8 = 2, 0.0, False
    return cfg


def _run(dataset, out, cfg, **kwargs) -> tuple[dict | None, dict[int, float]]:
    losses = {}

    def record(p):
        if "loss" in p.info:
            losses[p.info["step"]] = p.info["loss"]

    return train(dataset, out, cfg, progress=record, **kwargs), losses


def test_shards_weigh_to_the_whole_batch():
    items = list(range(5))
    parts = [shard(items, Ranks(r, 2, r)) for r in range(2)]
    assert parts[0] == ([0, 2, 4], 1.2) and parts[1] == ([1, 3], 0.8)
    assert sum(w for _, w in parts) / 2 == pytest.approx(1.0)  # DDP averages: the whole batch counts once
    assert shard([7], Ranks(1, 2, 1)) == ([7], 0.0) and shard(items, ONE) == (items, 1.0)


@pytest.mark.slow
def test_two_processes_match_one_and_resume(dataset, tmp_path):
    cfg = tiny()
    single, one = _run(dataset, tmp_path / "one", cfg)
    double, two = _run(dataset, tmp_path / "two", cfg, ddp=2)
    assert sorted(one) == sorted(two) == list(range(1, single["planned_steps"] + 1))
    for step in one:  # the same batches, the gradient averaged: only batch-norm statistics differ
        assert two[step] == pytest.approx(one[step], rel=0.02), (step, one, two)
    assert double["steps"] == single["steps"] and read_manifest(tmp_path / "two")["complete"]
    assert (tmp_path / "two" / "model.onnx").is_file()

    out, cancel = tmp_path / "resumed", threading.Event()

    def stop(p):
        if p.info.get("step") == 2:
            cancel.set()

    with pytest.raises(Cancelled):
        train(dataset, out, cfg, progress=stop, cancel=cancel, ddp=2)
    assert load_checkpoint(tmp_path / "resumed.partial" / "checkpoint.pt")["position"]["step"] == 2
    resumed, after = _run(dataset, out, cfg, ddp=2)
    assert min(after) == 3 and resumed["steps"] == resumed["planned_steps"]
    for step in after:
        assert after[step] == pytest.approx(two[step], rel=1e-3), (step, after, two)
