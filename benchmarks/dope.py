"""Benchmark of the DOPE stage: inference speed of both networks, the live node, and pose accuracy.

    python benchmarks/dope.py --model DOPE_MODEL --test TEST_DATASET [TEST_DATASET ...] [--views 24] [--node-seconds 20]
    python benchmarks/dope.py --train TRAIN_DATASET [TRAIN_DATASET ...] --minutes 60 --test TEST_DATASET

One table:
- per-frame inference time (onnxruntime, this CPU, 640x480 input) of the VGG DOPE network as published and of the
  light network, fp32 and static INT8 (VGG untrained: its cost does not depend on its weights);
- the light model's whole `detect` on a 640x480 camera image (resize to the trained scale, network, peaks, PnP);
- `dope_node` on a live stream: a 640x480 replay of the test frames at 30 Hz (the node's capacity: rate and
  end-to-end latency, stamp to published detection) and the simulated camera (`n2d launch sim`);
- ADD / ADD-S accuracy (10 % of the diameter) and AUC of the light model, fp32 and INT8, on the held-out
  synthetic test dataset, and on a turntable sweep captured like `n2d capture` does it (servo emulator + real
  driver + sim camera; ground truth from the board's camera poses and the object's place on the plate).
With `--train`, the light model is first trained on the TRAIN_DATASETs for `--minutes` (the CPU-hour of the issue).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from n2d_dope.data import open_dataset, read_rgb
from n2d_dope.evaluate import evaluate, evaluate_session
from n2d_dope.export import INPUT, OUTPUTS, export_onnx, quantize_int8, session
from n2d_dope.infer import DopeModel
from n2d_dope.network import DopeNet
from table import print_table

ACCURACY_GOAL = 0.80
"""ADD-S accuracy goal of the light model on held-out synthetic frames."""
FPS_GOAL = 10.0
"""End-to-end rate goal of the light model in the node, 2 CPU cores."""
SIZE = (640, 480)


def _time_session(path: Path, x: np.ndarray, runs: int) -> float:
    """Median seconds per run of an ONNX model on input `x` (after one warm-up run)."""
    s = session(path)
    s.run(list(OUTPUTS), {INPUT: x})
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        s.run(list(OUTPUTS), {INPUT: x})
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def _calibration(test: Path, count: int = 8) -> list[np.ndarray]:
    """`count` test frames at 640x480 as network inputs."""
    frames = open_dataset(test).frames[:count]
    images = [cv2.resize(read_rgb(f.image), SIZE, interpolation=cv2.INTER_LINEAR) for f in frames]
    return [np.ascontiguousarray((im.astype(np.float32) / 255).transpose(2, 0, 1)[None]) for im in images]


def speed_rows(model: Path, test: Path, tmp: Path, runs: int) -> list[tuple[str, ...]]:
    """Inference time of VGG and lite, fp32 and INT8, at 640x480; and the light model's whole detect()."""
    calibration = _calibration(test)
    x = calibration[0]
    rows = []
    vgg = tmp / "vgg.onnx"
    export_onnx(DopeNet("vgg", stages=6), vgg, SIZE)
    quantize_int8(vgg, tmp / "vgg_int8.onnx", calibration[:4])
    lite = DopeModel(model)
    for label, fp32, int8 in (("VGG-19 DOPE, 6 stages", vgg, tmp / "vgg_int8.onnx"),
                              (f"lite ({lite.config['backbone']}, {lite.config['stages']} stages)",
                               model / lite.config["models"]["fp32"], model / lite.config["models"].get("int8", ""))):
        for precision, path in (("fp32", fp32), ("INT8", int8)):
            if not path.is_file():
                continue
            seconds = _time_session(path, x, runs if "VGG" not in label else max(2, runs // 5))
            rows.append((f"{label} {precision}, 640x480 input", f"{1000 * seconds:.0f} ms",
                         f"{1 / seconds:.1f} FPS", ""))
    frame = open_dataset(test).frames[0]
    camera = json.loads((frame.chunk / "scene_camera.json").read_text())[str(frame.frame_id)]
    K = np.array(camera["cam_K"], dtype=float).reshape(3, 3)
    scale = SIZE[0] / read_rgb(frame.image).shape[1]
    rgb = cv2.resize(read_rgb(frame.image), SIZE, interpolation=cv2.INTER_LINEAR)
    K640 = np.diag([scale, scale, 1.0]) @ K
    for precision in lite.config["models"]:
        m = DopeModel(model, precision=precision)
        m.detect(rgb, K640)
        times = []
        for _ in range(runs):
            t0 = time.perf_counter()
            m.detect(rgb, K640)
            times.append(time.perf_counter() - t0)
        t = m.timing
        rows.append((f"lite detect() {precision} on a 640x480 image (net at {m.scale_for(K640):.2f}x)",
                     f"{1000 * np.median(times):.0f} ms", f"{1 / np.median(times):.1f} FPS",
                     f"pre {1000 * t.preprocess:.1f} / net {1000 * t.network:.1f} / "
                     f"post {1000 * t.postprocess:.1f} ms"))
    return rows


def _stream(model: Path, seconds: float, precision: str, replay: list | None) -> dict:
    """Run dope_node for `seconds` on the simulated camera (`replay` None) or on `replay` ((rgb, K) pairs) published
    at 30 Hz with fresh stamps; returns frames in, detections out, and latency (stamp -> detections received)."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CameraInfo, Image
    from vision_msgs.msg import Detection3DArray

    from n2d.launch_description import load
    from n2d.launcher import Launch
    from n2d_common.ros import (
        PUBLISH_QOS,
        background_node,
        camera_info_msg,
        image_msg,
        ros_environment,
        stamp_msg,
        stamp_seconds,
    )

    domain = 97 + os.getpid() % 4  # outside the tests' 1..88 (tests/conftest.py)
    ros_environment(domain)
    os.environ["ROS_DOMAIN_ID"] = str(domain)
    logs, latencies, frames_in = [], [], []
    with contextlib.ExitStack() as stack:
        if replay is None:
            stack.enter_context(Launch(load("sim"), {}, log=logs.append))
        stack.enter_context(Launch(load("dope"), {"models": str(model), "precision": precision}, log=logs.append))
        node = stack.enter_context(background_node("dope_benchmark", domain))
        every = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        arrivals = []

        def received(m) -> None:
            latencies.append(time.time() - stamp_seconds(m.header.stamp))
            arrivals.append(time.monotonic())

        node.create_subscription(Detection3DArray, "/n2d/dope/detections", received, every)
        if replay is None:  # the camera's rate; a replay counts what it publishes
            node.create_subscription(Image, "/n2d/camera/image_raw", lambda m: frames_in.append(1), every)
        image_pub = node.create_publisher(Image, "/n2d/camera/image_raw", PUBLISH_QOS) if replay else None
        info_pub = node.create_publisher(CameraInfo, "/n2d/camera/camera_info", PUBLISH_QOS) if replay else None
        deadline = time.monotonic() + 120
        while not node.count_publishers("/n2d/dope/detections") or (replay is None and not frames_in):
            if time.monotonic() > deadline:
                raise RuntimeError("dope_node did not come up:\n" + "\n".join(logs[-20:]))
            time.sleep(0.1)
        time.sleep(3.0)  # model loading and the first frames
        latencies.clear()
        arrivals.clear()
        frames_in.clear()
        t0 = time.monotonic()
        i = 0
        while time.monotonic() - t0 < seconds:
            if replay:
                rgb, K = replay[i % len(replay)]
                stamp = stamp_msg(time.time())
                info_pub.publish(camera_info_msg(K, rgb.shape[1], rgb.shape[0], stamp, "camera"))
                image_pub.publish(image_msg(rgb, "rgb8", stamp, "camera"))
                frames_in.append(1)
                i += 1
                time.sleep(max(0.0, t0 + i / 30.0 - time.monotonic()))
            else:
                time.sleep(0.1)
        elapsed = time.monotonic() - t0
    return {"fps_in": len(frames_in) / elapsed, "fps_out": len(latencies) / elapsed,
            "latency_ms": 1000 * np.array(latencies) if latencies else np.array([np.nan]),
            "arrivals_s": list(arrivals[:len(latencies)])}


def node_rows(model: Path, test: Path, seconds: float) -> list[tuple[str, ...]]:
    """dope_node on a 30 Hz 640x480 replay of the test frames (fp32 and INT8) and on the simulated camera."""
    replay = []
    for frame in open_dataset(test).frames[:30]:
        camera = json.loads((frame.chunk / "scene_camera.json").read_text())[str(frame.frame_id)]
        rgb = read_rgb(frame.image)
        scale = SIZE[0] / rgb.shape[1]
        K = np.diag([scale, scale, 1.0]) @ np.array(camera["cam_K"], dtype=float).reshape(3, 3)
        replay.append((cv2.resize(rgb, SIZE, interpolation=cv2.INTER_LINEAR), K))
    rows = []
    precisions = json.loads((model / "config.json").read_text())["models"]
    for label, frames, precision in ([("30 Hz 640x480 replay", replay, p) for p in precisions]
                                     + [("simulated camera", None, "fp32")]):
        r = _stream(model, seconds, precision, frames)
        fps = r["fps_out"]
        rows.append((f"dope_node {precision}, {label}: rate out / in", f"{fps:.1f} / {r['fps_in']:.1f} FPS",
                     f">= {FPS_GOAL:g} FPS" if frames is not None else "(bounded by the camera)",
                     ("met" if fps >= FPS_GOAL else "NOT met") if frames is not None else ""))
        rows.append(("  end-to-end latency (stamp -> detections received)",
                     f"{np.mean(r['latency_ms']):.0f} ms mean", f"p95 {np.percentile(r['latency_ms'], 95):.0f} ms",
                     ""))
    return rows


def accuracy_rows(model: Path, tests: list[Path], tmp: Path, views: int) -> list[tuple[str, ...]]:
    """ADD / ADD-S of the light model on each synthetic test set and all of them together (fp32, INT8), and on a
    captured turntable sweep."""
    rows = []
    config = json.loads((model / "config.json").read_text())
    for precision in config["models"]:
        results = []
        for i, test in enumerate(tests):
            r = evaluate(model, test, name="synthetic" if i == 0 else f"synthetic_{test.name}", precision=precision)
            results.append(r)
            rows += _accuracy(f"synthetic test set {test.name} {precision}", r,
                              f"{r['detected']}/{r['instances']} in {r['frames']} frames",
                              f"{r['adds_median_mm']:.1f} mm" if r["adds_median_mm"] is not None else "-")
        if len(results) > 1:
            # accuracy and AUC are means over instances, so the pooled value is the instance-weighted mean
            count = sum(r["instances"] for r in results)
            pooled = {k: sum(r[k] * r["instances"] for r in results) / count for k in
                      ("adds_accuracy_10pct", "add_accuracy_10pct", "adds_auc_10cm", "add_auc_10cm")}
            rows += _accuracy(f"all {len(results)} synthetic test sets {precision}", pooled,
                              f"{sum(r['detected'] for r in results)}/{count} in "
                              f"{sum(r['frames'] for r in results)} frames", "")
    if views:
        sys.path.insert(0, str(Path(__file__).parent))
        from capture import run as capture_run  # the capture benchmark's recording: the same code as n2d capture

        from n2d_capture.capture import CaptureConfig
        from n2d_capture.sweep import SweepConfig
        from n2d_sim.session import ground_truth
        from n2d_sim.world import SimWorldConfig

        world = SimWorldConfig(object=config["object"])
        sweep = tmp / "turntable"
        capture_run(sweep, world, CaptureConfig(sweep=SweepConfig(views=views)), overwrite=False)
        r = evaluate_session(model, sweep, T_turntable_obj=ground_truth(world).T_turntable_obj,
                             object_model_dir=ground_truth(world).model_dir)
        rows.append((f"turntable sweep ({views} views, board poses): ADD-S / ADD accuracy",
                     f"{100 * r['adds_accuracy_10pct']:.1f} % / {100 * r['add_accuracy_10pct']:.1f} %",
                     f"detected {r['detected']}/{r['instances']}",
                     f"AUC ADD-S {100 * r['adds_auc_10cm']:.1f}"))
    return rows


def _accuracy(label: str, r: dict, detected: str, median: str) -> list[tuple[str, ...]]:
    met = "met" if r["adds_accuracy_10pct"] >= ACCURACY_GOAL else "NOT met"
    return [(f"{label}: ADD-S / ADD accuracy",
             f"{100 * r['adds_accuracy_10pct']:.1f} % / {100 * r['add_accuracy_10pct']:.1f} %",
             f"ADD-S >= {100 * ACCURACY_GOAL:.0f} %", met),
            ("  AUC to 10 cm ADD-S / ADD; detected; median ADD-S",
             f"{100 * r['adds_auc_10cm']:.1f} / {100 * r['add_auc_10cm']:.1f}", detected, median)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--model", type=Path, help="a trained light DOPE model directory")
    parser.add_argument("--train", type=Path, nargs="+", help="train the light model on this dataset (or these, "
                        "rendered with the same camera) first")
    parser.add_argument("--minutes", type=float, default=60.0, help="training time with --train")
    parser.add_argument("--test", type=Path, nargs="+", required=True,
                        help="held-out test dataset(s) (other seeds); speed and the node use the first")
    parser.add_argument("--views", type=int, default=24, help="turntable sweep views (0: skip the sweep)")
    parser.add_argument("--runs", type=int, default=20, help="timed runs per network")
    parser.add_argument("--node-seconds", type=float, default=20.0, help="seconds of each live-stream run")
    args = parser.parse_args()
    if not args.model and not args.train:
        parser.error("give --model or --train")
    machine = f"{platform.processor() or platform.machine()}, {len(os.sched_getaffinity(0))} cores"
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        model = args.model
        rows = []
        if args.train:
            from n2d_dope.config import TIMED_EPOCHS, TrainConfig
            from n2d_dope.train import train

            model = model or tmp / "dope"
            cfg = TrainConfig(epochs=TIMED_EPOCHS, max_minutes=args.minutes)
            train(args.train, model, cfg)
        summary = json.loads((model / "training.json").read_text())
        init = json.loads((model / "n2d.json").read_text())["inputs"].get("init_model")
        rows.append(("light model training (CPU)", f"{summary['train_seconds'] / 60:.0f} min",
                     f"{summary['steps']} steps on {summary['train_frames']} frames"
                     + (f", fine-tuned from {Path(init).name}" if init else ""),
                     f"held-out loss {summary['held_out_loss']:.5f}" if summary["held_out_loss"] else ""))
        rows += speed_rows(model, args.test[0], tmp, args.runs)
        if args.node_seconds > 0:
            rows += node_rows(model, args.test[0], args.node_seconds)
        rows += accuracy_rows(model, args.test, tmp, args.views)
    print_table(f"dope: {machine}", rows, ("metric", "value", "goal / note", ""))


if __name__ == "__main__":
    main()
