"""`n2d pipeline` for a list of objects: on a real local Ray cluster (a head and a worker node started with `ray
start` on loopback) two objects run their dataset stage as tasks, one of them with a broken model: the other
finishes with its dataset, the broken one is reported with its error. The same command again (without the
cluster, one object after another) keeps the finished dataset and reports the same error, and once the broken
model is fixed finishes it. Bad input (a repeated or unknown object, an unreachable cluster) is one error line
with a hint and writes nothing."""

import json
import os
import shutil
import subprocess
import sys

import pytest
import yaml
from helpers import LocalCluster, free_port

from n2d.cli import main
from n2d_common.contracts import open_stage, read_manifest
from n2d_sim.objects import sample_object_dir

BOX = sample_object_dir("box")
TINY = {"frames": 4, "test_frames": 0, "test_views": 0,
        "dataset": {"camera": {"width": 160, "height": 120, "focal_px": 150.0}, "render": {"engine": "raster"},
                    "workers": 1, "scene": {"distractors": [1, 2]}}}
"""The smallest dataset stage: 4 raster frames of 160 x 120 in one render process."""


@pytest.fixture
def inputs(tmp_path):
    """(config file, objects: box from the sample model, broken from a copy of it without its mesh)."""
    config = tmp_path / "tiny.yaml"
    config.write_text(yaml.safe_dump(TINY))
    broken = tmp_path / "broken_model"
    shutil.copytree(BOX, broken)
    (broken / "mesh.obj").unlink()
    return config, f"box={BOX},broken={broken}"


def _pipeline(run_dir, objects, config, *more):
    return [sys.executable, "-m", "n2d.cli", "pipeline", str(run_dir), "--objects", objects, "--stages", "dataset",
            "--config", str(config), *more]


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_objects_on_a_cluster_fail_alone_and_resume(inputs, tmp_path):
    config, objects = inputs
    runs = tmp_path / "runs"
    nodes = LocalCluster()
    try:
        nodes.start("head", head=True)
        nodes.start("worker", head=False)
        run = subprocess.run(_pipeline(runs, objects, config, "--cluster", nodes.address), capture_output=True,
                             text=True, timeout=240)
    finally:
        nodes.stop()
    log = run.stdout + run.stderr
    assert run.returncode == 2, log[-3000:]
    assert f"pipeline: box: dataset done, in {runs / 'box'}/" in run.stdout, log[-3000:]
    assert "pipeline: broken: failed: stage dataset: " in run.stderr and "has no mesh.obj" in run.stderr, log[-3000:]
    assert "1 of 2 objects finished; failed: broken" in run.stdout
    assert "box: 100%" in run.stderr  # its progress came back from the task

    dataset = open_stage(runs / "box" / "dataset", "dataset")
    assert len(list((runs / "box" / "dataset").rglob("rgb/*.jpg"))) == TINY["frames"]
    status = json.loads((runs / "box" / "run.json").read_text())
    assert list(status["stages"]) == ["dataset"]
    assert not (runs / "broken" / "dataset").exists() and not (runs / "broken" / "run.json").exists()
    assert not (runs / ".n2d_cluster_check").exists()

    # the same command again, here: the finished object is kept as it was, the broken one fails the same way
    again = subprocess.run(_pipeline(runs, objects, config), capture_output=True, text=True, timeout=120)
    assert again.returncode == 2 and "has no mesh.obj" in again.stderr, (again.stdout + again.stderr)[-3000:]
    assert json.loads((runs / "box" / "run.json").read_text()) == status
    assert read_manifest(runs / "box" / "dataset") == dataset
    assert f"{runs / 'broken' / 'model'} is the copy of" in again.stderr

    # the source fixed and its copy deleted, as the hint says: the broken object finishes, the other is untouched
    shutil.copy(BOX / "mesh.obj", tmp_path / "broken_model" / "mesh.obj")
    shutil.rmtree(runs / "broken" / "model")
    fixed = subprocess.run(_pipeline(runs, objects, config), capture_output=True, text=True, timeout=120)
    assert fixed.returncode == 0 and "2 of 2 objects finished" in fixed.stdout, (fixed.stdout + fixed.stderr)[-3000:]
    assert open_stage(runs / "broken" / "dataset", "dataset")["complete"]
    assert json.loads((runs / "box" / "run.json").read_text()) == status


@pytest.mark.parametrize("objects, words", [
    ("box,box", ["object box is listed twice", "list each object once"]),
    ("box,mug", ["object mug: no run directory", "mug=CAPTURE_SESSION_OR_MODEL_DIR"]),
    ("box,my mug", ["'my mug' is not usable"]),
    ("box=/nowhere", ["/nowhere of object box is no capture session or model"]),
])
def test_bad_object_lists_are_refused(tmp_path, capsys, objects, words):
    runs = tmp_path / "runs"
    objects = objects.replace("box,", f"box={BOX},", 1)
    assert main(["pipeline", str(runs), "--objects", objects, "--stages", "dataset"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err[0].startswith("n2d: error: ") and err[1].startswith("  hint: ") and len(err) == 2, err
    assert all(w in "\n".join(err) for w in words), err
    assert not runs.exists()


def test_an_unreachable_cluster_is_refused(tmp_path, capsys):
    runs, address = tmp_path / "runs", f"127.0.0.1:{free_port()}"
    assert main(["pipeline", str(runs), "--objects", f"box={BOX}", "--cluster", address,
                 "--set", "test_views=0"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert err[0] == f"n2d: error: cannot reach the Ray cluster at {address} (Connection refused)", err
    assert "ray start --head" in err[1] and not runs.exists()


def test_capture_stages_are_refused_and_nothing_is_written(tmp_path, capsys):
    runs = tmp_path / "runs"
    assert main(["pipeline", str(runs), "--objects", f"box={BOX}", "--stages", "capture,reconstruct"]) == 2
    assert "drive the turntable" in capsys.readouterr().err and not runs.exists()
    (tmp_path / "one").mkdir()
    (tmp_path / "one" / "IMG_0001.jpg").write_bytes(b"")
    assert main(["pipeline", str(tmp_path), "--objects", f"one={BOX}"]) == 2  # a foreign directory in the way
    assert "object one: " in capsys.readouterr().err and os.listdir(tmp_path / "one") == ["IMG_0001.jpg"]


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_an_object_from_its_capture_session_runs_every_stage_in_this_process(tmp_path, capsys):
    """The stages after the captures as library calls, from a session to an evaluated DOPE model: the one path
    `LibraryStages` takes that the cluster test (dataset only) does not."""
    from n2d_sim.session import render_session, small_world

    session = tmp_path / "session"
    render_session(session, small_world("box", 160, 120), views=12)
    small = {"camera": {"width": 160, "height": 120, "focal_px": 150.0}, "render": {"engine": "raster"},
             "workers": 1, "scene": {"distractors": [0, 1]}}
    config = tmp_path / "all.yaml"
    config.write_text(yaml.safe_dump({
        "frames": 4, "test_frames": 2, "test_views": 0, "preset": "tiny", "precisions": ["fp32"],
        "reconstruct": {"mesh": {"voxel_m": 0.004, "target_faces": 2000}, "texture": {"size_px": 64},
                        "refine": {"enabled": False}},
        "dataset": small, "test_dataset": small, "train": {"epochs": 2}}))
    runs = tmp_path / "runs"
    assert main(["pipeline", str(runs), "--objects", f"box={session}", "--config", str(config)]) == 0, \
        capsys.readouterr().err[-3000:]
    assert "1 of 1 objects finished" in capsys.readouterr().out
    status = json.loads((runs / "box" / "run.json").read_text())
    assert list(status["stages"]) == ["reconstruct", "dataset", "test_dataset", "train", "evaluate"]
    for out, kind in (("model", "model"), ("dataset", "dataset"), ("dataset_test", "dataset"),
                        ("dope", "dope_model")):
        assert open_stage(runs / "box" / out, kind)["complete"], out
    assert (runs / "box" / "dope" / "model.onnx").is_file()
    scores = status["stages"]["evaluate"]["summary"]["synthetic"]["fp32"]  # scored, not how well: 2 epochs
    assert scores["images"] == 2 and scores["instances"] >= 1 and 0.0 <= scores["adds_accuracy_10pct"] <= 1.0
