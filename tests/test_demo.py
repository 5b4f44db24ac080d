"""`n2d demo` end to end, as a user runs it: a subprocess that starts the simulated world, every stage node and
pipeline_node, drives the Pipeline action through real rclpy, and scores dope_node live; Ctrl-C in the middle
and the same command continues from the last finished stage.

Tiny configs keep it to minutes on 2 cores: 12 views (at 640x480: the board needs the pixels) carved into a
plain visual hull, an 8-frame dataset at 160x120, and the tiny DOPE network trained without augmentation for
300 epochs, which memorises its 8 frames. So the pose tolerance below (median ADD-S <= 15 mm of a ~180 mm
box, on those frames) checks that units, frames and cuboid conventions hold from the capture to the pose, not
how well such a model generalises.
"""

import json
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from n2d.pipeline import STAGES, RunLayout
from n2d_common.contracts import open_stage
from n2d_common.images import read_png

pytestmark = pytest.mark.slow  # real rendering, training or ROS round trips: tens of seconds or more

TINY = {
    "live_views": 2, "live_frames": 2,
    "pipeline.views": 12, "pipeline.test_views": 4, "pipeline.frames": 8, "pipeline.test_frames": 4,
    "pipeline.preset": "tiny",
    "pipeline.reconstruct": {"mesh": {"voxel_m": 0.003, "target_faces": 3000}, "texture": {"size_px": 128},
                             "refine": {"enabled": False}},
    "pipeline.dataset": {"camera": {"width": 160, "height": 120, "focal_px": 150.0}, "render": {"samples": 2}},
    "pipeline.test_dataset": {"camera": {"width": 160, "height": 120, "focal_px": 150.0}, "render": {"samples": 2}},
    # the windows at the tiny frames' own scale (the default recipe's go with its 320 x 320 frames at 900 px)
    "pipeline.train": {"epochs": 300, "zoom": 1.0, "input_size": [160, 128],
                       "augment": {"scale": [1.0, 1.0], "rotate_deg": 0.0, "shift": 0.0, "background_swap": 0.0,
                                   "noise": 0.0, "blur": 0.0}},
}
KINDS = {"capture": "capture_session", "test_capture": "capture_session", "reconstruct": "model",
         "dataset": "dataset", "test_dataset": "dataset", "train": "dope_model"}


def _command(out: Path, domain: int) -> list[str]:
    n2d = shutil.which("n2d", path=str(Path(sys.executable).parent))
    sets = [f"{k}={json.dumps(v)}" for k, v in {**TINY, "domain_id": domain}.items()]
    return [n2d, "demo", str(out), *[a for s in sets for a in ("--set", s)]]


@pytest.mark.timeout(1200)
def test_demo_runs_the_pipeline_resumes_after_ctrl_c_and_scores_poses(tmp_path, ros_domain):
    out = tmp_path / "run"
    layout = RunLayout(out)
    cmd = _command(out, ros_domain)

    # Ctrl-C while the network trains: the finished stages stay, and so does the training's checkpoint
    log = tmp_path / "first.log"  # a file, not a pipe: a full pipe would block the demo's progress output
    with open(log, "w") as sink:
        # A shell runs background jobs with SIGINT ignored, and Python keeps an ignored SIGINT: give the demo
        # the default, as a terminal would.
        first = subprocess.Popen(cmd, stdout=sink, stderr=subprocess.STDOUT, text=True,
                                 preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 900
        while not (out / "dope.partial" / "checkpoint.pt").is_file():
            assert first.poll() is None, log.read_text()[-3000:]
            assert time.monotonic() < deadline, "the train stage did not start"
            time.sleep(0.5)
        first.send_signal(signal.SIGINT)
        assert first.wait(timeout=120) == 130, log.read_text()[-3000:]
    finally:
        if first.poll() is None:  # a failed test must not leave the demo and its nodes running
            first.kill()
            first.wait()
    before = json.loads((out / "run.json").read_text())["stages"]
    assert set(before) == {"empty_plate", "capture", "test_capture", "reconstruct", "dataset", "test_dataset"}
    assert not json.loads((out / "n2d.json").read_text())["complete"]

    again = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
    assert again.returncode == 0, (again.stdout + again.stderr)[-3000:]
    assert "per stage:" in again.stdout and "live dope_node" in again.stdout

    # every stage's output is complete, and the stages finished before Ctrl-C were not run again
    manifest = open_stage(out, "run")
    assert manifest["config"]["object_name"] == "box"
    status = json.loads((out / "run.json").read_text())["stages"]
    assert set(status) == {"empty_plate", *STAGES}
    for stage in before:
        assert status[stage] == before[stage]
    for stage, kind in KINDS.items():
        assert open_stage(layout.output(stage), kind)["complete"]
    assert (out / "capture" / "empty.json").is_file()  # the empty-plate sweep, the masks' background reference

    # the reconstruction is metric: a visual hull holds the object, so it is at least the box's size and, from
    # 12 views, not much more
    from n2d_sim.objects import sample_object_dir

    truth = json.loads((sample_object_dir("box") / "models_info.json").read_text())
    ours = json.loads((layout.output("reconstruct") / "models_info.json").read_text())
    size = np.array([_entry(ours)[f"size_{a}"] for a in "xyz"])
    true_size = np.array([_entry(truth)[f"size_{a}"] for a in "xyz"])
    assert np.all(size >= 0.97 * true_size) and np.all(size <= 1.3 * true_size), (size, true_size)

    # the pose tolerance (see the module doc): the model on the frames it was trained on
    from n2d_dope.evaluate import evaluate

    r = evaluate(layout.output("train"), layout.output("dataset"), name="training_frames")
    assert r["detected"] >= 0.75 * r["instances"], r
    assert r["adds_median_mm"] is not None and r["adds_median_mm"] <= 15.0, r

    # the evaluation stage scored both test sets, the live check scored dope_node's poses
    demo = json.loads((out / "demo.json").read_text())
    assert set(demo["evaluation"]) == {"synthetic", "turntable"}
    assert demo["evaluation"]["turntable"]["fp32"]["instances"] == 4
    # and the poses refined against the images, as dope_node publishes them
    assert demo["evaluation"]["turntable"]["fp32 refined"]["instances"] == 4
    live = demo["live"]
    assert live["instances"] == 4 and live["processed_frames"] >= 4
    assert read_png(out / "live" / "overlays.png").ndim == 3
    assert set(demo["seconds"]) == {"empty_plate", *STAGES, "live"}

    rerun = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert rerun.returncode == 0 and "complete already" in rerun.stdout


def _entry(info: dict) -> dict:
    return next(iter(info.values())) if "diameter" not in info else info
