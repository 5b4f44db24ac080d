"""`n2d demo`: the whole job on the embedded default world (simulated servo + camera + a sample object).

It starts what `n2d launch pipeline` starts (the simulated world, the stage nodes and pipeline_node) and acts
as a task planner would: it clears the plate (the simulator lifts the object) for the empty-plate sweep, puts
the object back and sends one `Pipeline` goal: capture, test sweep, reconstruction, dataset, training,
evaluation, one progress display over all of them. With `pipeline.placements: 2` the test sweep runs first,
and when the capture stage asks for the object to be turned over (capture_node's `turn_over` feedback) the
demo turns the simulated object over (`sim/turn_over`) and calls `capture/continue`; the reconstruction fuses
the two placements into a closed model, and the object is stood back as it first stood for the live check.
Then the live check: `dope_node` runs the new model on the simulated camera while the plate turns to angles no
sweep used, and each published pose is scored against the simulator's ground truth (ADD / ADD-S with the
reconstructed model's points). Everything lands in one run directory; Ctrl-C at any stage and the same command
continues from the last finished stage (the unfinished one resumes from its partial output).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from n2d.pipeline import EMPTY_PLATE, PipelineConfig, RunLayout, check_object_name, check_run_dir
from n2d_common.config import to_dict
from n2d_common.contracts import atomic_write_json, read_manifest
from n2d_common.errors import ContractError, DeviceError
from n2d_common.frames import inv_T
from n2d_common.images import contact_sheet, write_png
from n2d_common.progress import Progress, ProgressFn, no_progress

LIVE_DIR = "live"
"""Where the live check writes, inside the run directory."""


def _demo_pipeline() -> PipelineConfig:
    # The pipeline's own recipe (fast training frames, timed training), sized to keep the demo within 30 min on
    # 2 CPU cores: 1200 frames of the reconstructed model (its 40k faces render at about 3.4 frames/s) and 10
    # minutes of training; the held-out synthetic test set is small (16 Cycles frames at half size, 8 samples
    # per pixel). The capture keeps the pipeline's 36 views: fewer leave the box's plain sides bulging.
    small = {"camera": {"width": 320, "height": 240, "focal_px": 300.0, "distance_m": [0.3, 0.7]},
             "render": {"samples": 8}}
    return PipelineConfig(views=36, test_views=8, frames=1200, train_minutes=10.0, test_frames=16,
                          test_dataset=small)


@dataclass
class DemoConfig:
    """What `n2d demo` runs."""

    object: str = "box"
    """Sample object of the simulated world (box, bottle) or a model directory."""
    name: str = ""
    """Name the pipeline gives the object; empty: the sample's name."""
    width: int = 640
    """Simulated camera image width (px)."""
    height: int = 480
    """Simulated camera image height (px)."""
    focal_px: float = 600.0
    """Simulated camera focal length (px); scale it with the image size."""
    empty_plate: bool = True
    """Record the empty-plate sweep first (the background reference of the masks)."""
    pipeline: PipelineConfig = field(default_factory=_demo_pipeline)
    """The run (views, frames, training time, stage overrides)."""
    live_views: int = 12
    """Plate stops of the live check, a quarter step off the sweeps' angles (0: no live check)."""
    live_frames: int = 3
    """dope_node results scored at each stop."""
    live_precision: str = "fp32"
    """Model dope_node runs in the live check (fp32, int8)."""
    domain_id: int = -1
    """ROS_DOMAIN_ID of the private simulated world; -1: derived from the process id."""
    startup_timeout_s: float = 180.0
    """How long to wait for the nodes to come up (the sim camera's first render builds its scene)."""

    def __post_init__(self):
        if self.width < 32 or self.height < 32:
            raise ValueError("width and height must be >= 32 px")
        if self.live_views < 0 or self.live_frames < 1:
            raise ValueError("live_views must be >= 0 and live_frames >= 1")
        if self.live_precision not in ("fp32", "int8"):
            raise ValueError(f"live_precision is fp32 or int8, got {self.live_precision!r}")

    def object_name(self) -> str:
        return check_object_name(self.name or Path(self.object).name)


def run_demo(out: str | Path, cfg: DemoConfig, *, overwrite: bool = False, progress: ProgressFn = no_progress,
             log=print) -> dict:
    """Run the demo into the run directory `out` and return its summary (also `out/demo.json`)."""
    import yaml

    from n2d.launch_description import load
    from n2d.launcher import Launch
    from n2d_common.ros import SafeActionClient, background_node, call_action, ros_environment
    from n2d_interfaces.action import Pipeline

    out = Path(out).absolute()
    layout = RunLayout(out)
    summary_file = out / "demo.json"
    name = cfg.object_name()
    manifest = check_run_dir(out, name, cfg.pipeline, overwrite)  # before anything starts
    if manifest and manifest.get("complete") and summary_file.is_file() and not overwrite:
        log(f"{out} is complete already (pass --overwrite to run again)")
        return json.loads(summary_file.read_text())

    t_start = time.monotonic()
    domain = cfg.domain_id if cfg.domain_id >= 0 else 1 + os.getpid() % 100
    env = ros_environment(domain, env=dict(os.environ))
    os.environ.update(env)
    logs: list[str] = []
    with contextlib.ExitStack() as stack:
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="n2d_demo_")))  # pty link, control socket
        world_args = {"object": cfg.object, "port": str(tmp / "ttyDXL"), "control": str(tmp / "servo.ctl"),
                      "width": str(cfg.width), "height": str(cfg.height), "focal_px": str(cfg.focal_px)}
        progress(Progress(0.0, "starting", message="simulated world, stage nodes, pipeline_node"))
        launch = stack.enter_context(Launch(load("pipeline"), world_args, env=env, log=logs.append))
        node = stack.enter_context(background_node("n2d_demo"))
        client = SafeActionClient(node, Pipeline, "/n2d/pipeline")
        if not client.wait_for_server(timeout_sec=cfg.startup_timeout_s):
            raise DeviceError(_startup_failure(launch, logs))
        config_yaml = yaml.safe_dump(to_dict(cfg.pipeline))

        def pipeline(stages: list[str], start: float, share: float, overwrite: bool, watch=None):
            """Send a Pipeline goal; its progress fills [start, start + share] of the demo's; `watch` sees each
            feedback too."""
            goal = Pipeline.Goal(object_name=name, run_dir=str(out), config_yaml=config_yaml, stages=stages,
                                 overwrite=overwrite)

            def feedback(fb) -> None:
                progress(Progress(start + share * fb.progress, f"{fb.stage_index}/{fb.stages_total} {fb.stage}",
                                  fb.eta_s, fb.message))
                if watch is not None:
                    watch(fb)

            return call_action(client, goal, what="pipeline", feedback=feedback)

        status = json.loads((out / "run.json").read_text()) if (out / "run.json").is_file() else {}
        empty_sweep = cfg.empty_plate and (overwrite or not layout.done(EMPTY_PLATE, status))
        if empty_sweep:
            _set_object_visible(node, False, cfg.startup_timeout_s)
            pipeline([EMPTY_PLATE], 0.0, 0.05, overwrite)
            _set_object_visible(node, True, 30.0)
        if cfg.pipeline.placements > 1 and not overwrite and _turned_over(layout, status):
            _sim_switch(node, "turn_over", True, 60.0)  # a fresh world, resuming the second sweep: as it was
        with _TurnOver(node, cfg.startup_timeout_s) as turner:
            status = json.loads(pipeline([], 0.05, 0.9, overwrite and not empty_sweep, watch=turner.watch).summary_json)
        if cfg.pipeline.placements > 1:
            _sim_switch(node, "turn_over", False, 60.0)  # as it first stood, in the model's frame, for the live check
        live = None
        if cfg.live_views:
            progress(Progress(0.95, "live", message="dope_node on the simulated camera"))
            live = live_check(node, layout, cfg, env)
    progress(Progress(1.0, "done"))
    summary = {"object": name, "run_dir": str(out), "seconds_total": round(time.monotonic() - t_start, 1),
               "seconds": {s: v["seconds"] for s, v in status["stages"].items()},
               "evaluation": status["stages"]["evaluate"]["summary"], "live": live,
               "placements": status["stages"]["reconstruct"]["summary"].get("placements")}
    if live is not None:
        summary["seconds"]["live"] = live["seconds"]
    atomic_write_json(summary_file, summary)
    return summary


def _startup_failure(launch, logs: list[str]) -> str:
    dead = launch.dead()
    what = f"{dead[0][0]} exited with code {dead[0][1]}" if dead else "the pipeline action did not come up"
    return f"the pipeline nodes failed to start ({what}); last log lines:\n" + "\n".join(logs[-15:])


def _set_object_visible(node, visible: bool, timeout_s: float) -> None:
    """Lift the simulated object off the plate or put it back (the sim camera's service)."""
    _sim_switch(node, "set_object_visible", visible, timeout_s)


def _turned_over(layout: RunLayout, status: dict) -> bool:
    """Whether the run's unfinished capture had the object turned over already (its second sweep resumes)."""
    from n2d_capture.capture import PLACEMENT_FILE

    return not layout.done("capture", status) and (layout.root / "capture.partial" / PLACEMENT_FILE).is_file()


def _call(node, srv_type, name: str, request, timeout_s: float):
    """Call the service `name` once (waiting `timeout_s` for it to appear); DeviceError when it fails."""
    from n2d_common.ros import wait_future

    client = node.create_client(srv_type, name)
    try:
        if not client.wait_for_service(timeout_sec=timeout_s):
            raise DeviceError(f"the service {name} is not available")
        response = wait_future(client.call_async(request), 60.0, name)
    finally:
        node.destroy_client(client)
    if not response.success:
        raise DeviceError(f"{name} refused: {response.message}")
    return response


def _sim_switch(node, service: str, on: bool, timeout_s: float) -> None:
    """One of the sim camera's std_srvs/SetBool services: set_object_visible, turn_over."""
    from std_srvs.srv import SetBool

    _call(node, SetBool, f"/n2d/sim/{service}", SetBool.Request(data=on), timeout_s)


class _TurnOver:
    """While the capture stage runs: when it asks for the object to be turned over (the Pipeline feedback of the
    capture stage in stage `turn_over`), turn the simulated object over and call capture_node's `capture/continue`,
    as a person or a robot arm would. In a thread of its own: the feedback arrives on the node's executor thread."""

    def __init__(self, node, timeout_s: float):
        self.node, self.timeout_s = node, timeout_s
        self.asked, self.stop = threading.Event(), threading.Event()
        self.error: Exception | None = None
        self.thread = threading.Thread(target=self._run, daemon=True)

    def watch(self, fb) -> None:
        from n2d_capture.capture import TURN_OVER

        if fb.stage == "capture" and fb.message.startswith(TURN_OVER):
            self.asked.set()

    def _run(self) -> None:
        from std_srvs.srv import Trigger

        while not self.stop.is_set():
            if not self.asked.wait(0.2):
                continue
            try:
                _sim_switch(self.node, "turn_over", True, self.timeout_s)
                _call(self.node, Trigger, "/n2d/capture/continue", Trigger.Request(), self.timeout_s)
            except DeviceError as exc:
                self.error = exc
            return  # two placements: one turn

    def __enter__(self) -> _TurnOver:
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop.set()
        self.thread.join(timeout=120.0)
        if self.error is not None and exc[0] is None:
            raise self.error


class _LiveRecorder:
    """Collects, by image stamp, the simulator's true object poses, dope_node's detections and overlays."""

    def __init__(self, node):
        from geometry_msgs.msg import PoseStamped
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import Image
        from std_msgs.msg import Float64
        from vision_msgs.msg import Detection3DArray

        from n2d_common.ros import SENSOR_QOS

        self.lock = threading.Lock()
        self.truth: dict[int, object] = {}
        self.detections: list = []
        self.overlays: dict[int, object] = {}
        self.latency_ms: list[float] = []
        reliable = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
        self.subs = [
            node.create_subscription(PoseStamped, "/n2d/sim/object_pose", lambda m: self._keep(self.truth, m),
                                     SENSOR_QOS),
            node.create_subscription(Detection3DArray, "/n2d/dope/detections", self._on_detections, reliable),
            node.create_subscription(Image, "/n2d/dope/overlay", lambda m: self._keep(self.overlays, m, 20), reliable),
            node.create_subscription(Float64, "/n2d/dope/latency_ms", lambda m: self.latency_ms.append(m.data),
                                     reliable)]

    @staticmethod
    def key(stamp) -> int:
        return stamp.sec * 1_000_000_000 + stamp.nanosec

    def _keep(self, store: dict, msg, limit: int = 200) -> None:
        with self.lock:
            store[self.key(msg.header.stamp)] = msg
            while len(store) > limit:
                store.pop(next(iter(store)))

    def _on_detections(self, msg) -> None:
        with self.lock:
            self.detections.append(msg)

    def after(self, t_s: float) -> list:
        """Detection arrays of images stamped at or after `t_s` whose ground truth has arrived."""
        with self.lock:
            return [d for d in self.detections
                    if self.key(d.header.stamp) >= t_s * 1e9 and self.key(d.header.stamp) in self.truth]


def live_check(node, layout: RunLayout, cfg: DemoConfig, env: dict) -> dict:
    """Run dope_node on the simulated camera, turn the plate through `cfg.live_views` new angles and score the
    published poses against the simulator's ground truth; writes `live/live.json` and `live/overlays.png`."""
    from n2d.launch_description import load
    from n2d.launcher import Launch
    from n2d_capture.nodes.ros_io import RosRotator
    from n2d_common.frames import R_from_quat, make_T
    from n2d_common.ros import image_rgb
    from n2d_dope.evaluate import model_points
    from n2d_dope.metrics import add, add_s, summarize
    from n2d_sim.world import SimWorldConfig, T_plate_obj

    t0 = time.monotonic()
    model_dir, dope_dir = layout.output("reconstruct"), layout.output("train")
    stored = (read_manifest(model_dir) or {}).get("extra", {}).get("T_turntable_obj")
    if stored is None:
        raise ContractError(f"{model_dir} does not record T_turntable_obj", "reconstruct it with this n2d")
    # Both the reconstructed model and the simulator's object stand still on the plate, and the session's
    # turntable frame is the plate frame at the first view: so this is fixed for the whole check.
    T_simobj_obj = inv_T(T_plate_obj(SimWorldConfig(object=cfg.object))) @ np.array(stored, dtype=float)
    points, diameter = model_points(model_dir)

    def pose_T(pose) -> np.ndarray:
        q = pose.orientation
        return make_T(R_from_quat([q.x, q.y, q.z, q.w]), [pose.position.x, pose.position.y, pose.position.z])

    name = cfg.object_name()
    recorder = _LiveRecorder(node)
    rotator = RosRotator(node, "/n2d/turntable/rotate")
    add_errors, adds_errors, sheet, labels, records = [], [], [], [], []
    logs: list[str] = []
    with Launch(load("dope"), {"models": str(dope_dir), "precision": cfg.live_precision}, env=env,
                log=logs.append) as dope:
        for i in range(cfg.live_views):
            angle = 2 * math.pi * (i + 0.25) / cfg.live_views
            reached = rotator.rotate_to(angle)
            settled = time.time()
            deadline = time.monotonic() + (cfg.startup_timeout_s if i == 0 else 30.0)
            while len(recorder.after(settled)) < cfg.live_frames:
                if dope.dead() or time.monotonic() > deadline:
                    raise DeviceError(f"dope_node published no poses for the live check (stop {i + 1})",
                                      "last log lines:\n" + "\n".join(logs[-15:]))
                time.sleep(0.05)
            for msg in recorder.after(settled)[:cfg.live_frames]:
                key = recorder.key(msg.header.stamp)
                truth = pose_T(recorder.truth[key].pose) @ T_simobj_obj
                ours = [d for d in msg.detections if d.results and d.results[0].hypothesis.class_id == name]
                best = max(ours, key=lambda d: d.results[0].hypothesis.score, default=None)
                if best is None:
                    errors = (math.inf, math.inf)
                else:
                    T_est = pose_T(best.results[0].pose.pose)
                    errors = (add(T_est, truth, points), add_s(T_est, truth, points))
                add_errors.append(errors[0])
                adds_errors.append(errors[1])
                records.append({"stop": i, "plate_rad": reached, "stamp_ns": key, "detected": best is not None,
                                "add_mm": None if best is None else 1000 * errors[0],
                                "adds_mm": None if best is None else 1000 * errors[1]})
            first = recorder.after(settled)[0]
            overlay = recorder.overlays.get(recorder.key(first.header.stamp))
            if overlay is not None:
                error = records[-cfg.live_frames]["add_mm"]
                sheet.append(image_rgb(overlay))
                labels.append(f"{math.degrees(reached):5.1f} deg "
                              + ("missed" if error is None else f"ADD {error:.0f} mm"))
        seconds = time.monotonic() - t0
        processed = len(recorder.detections)
    for sub in recorder.subs:
        node.destroy_subscription(sub)
    result = {**summarize(add_errors, adds_errors, diameter), "precision": cfg.live_precision,
              "views": cfg.live_views, "frames_per_view": cfg.live_frames, "processed_frames": processed,
              "latency_ms_mean": float(np.mean(recorder.latency_ms)) if recorder.latency_ms else None,
              "seconds": round(seconds, 1)}
    live_dir = layout.root / LIVE_DIR
    live_dir.mkdir(exist_ok=True)
    if sheet:
        write_png(live_dir / "overlays.png", contact_sheet(sheet, labels))
    atomic_write_json(live_dir / "live.json", {**result, "frames": records})
    return result
