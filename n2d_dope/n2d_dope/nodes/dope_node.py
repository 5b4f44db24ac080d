"""dope_node: live 6D poses of the trained objects in a camera stream (DOPE models on ONNX Runtime).

Subscribes to any camera driver's `image_topic` + `camera_info_topic` (undistorted images) with live-video QoS:
depth 1 (reliable, best effort for best-effort publishers), so a node slower than the camera drops stale frames
instead of queueing them. The subscription callbacks only keep the newest image and CameraInfo; one worker thread
processes the newest image (at most `max_rate_hz` times a second) and publishes.

With `refine` (the default) every detected pose is refined against the image with the object's model and
dropped when it does not fit (`n2d_dope.pose_refine`); with `track` (the default) each object is then followed
from frame to frame by refinement (`n2d_dope.track`) while a second worker runs the network when an object is
not tracked and every `redetect_frames` frames, so the poses keep the camera's rate. A DOPE directory without
its object's model (trained by an older n2d, moved without the model it names) only detects.

Published under the node's namespace: `dope/pose_<object>` (PoseStamped, the best pose of each object, only
when found), `dope/detections` (Detection3DArray, one per processed frame, empty when nothing was found; each
detection's `id` is `<object>:detected` or `<object>:tracked`, its score the network's confidence or, refined
or tracked, the silhouette score 0..1), `dope/overlay` (rgb8, the fitted cuboids and object axes drawn) and
`dope/latency_ms` (Float64, image stamp to published detections), `dope/markers` (MarkerArray, each object's
mesh at its best pose, `publish_scene`); on `/tf` (`publish_tf`) each object's frame `tf_prefix` + name (`n2d/box`)
under the camera's frame; and, where moveit_msgs is installed, each object on `/collision_object`
(`n2d_dope.nodes.scene_msgs`). Detections are `vision_msgs` messages. Poses are
in the camera's OpenCV optical frame, metres; each header is the image's, with `camera_frame` as frame_id when
set. Every `log_period_s` it logs frames received, frames processed and the latency.
"""

from __future__ import annotations

import re
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
from geometry_msgs.msg import PoseStamped, PoseWithCovariance, Transform, TransformStamped, Vector3
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Float64, Header
from tf2_msgs.msg import TFMessage
from vision_msgs.msg import (
    BoundingBox3D,
    Detection3D,
    Detection3DArray,
    ObjectHypothesis,
    ObjectHypothesisWithPose,
)
from visualization_msgs.msg import MarkerArray

from n2d_common.errors import ConfigError, N2DError
from n2d_common.frames import project, transform_points
from n2d_common.images import draw_axes, draw_cuboid
from n2d_common.ros import (
    PUBLISH_QOS,
    TF_QOS,
    LiveSubscription,
    declare_config,
    image_msg,
    image_rgb,
    pose_msg,
    run_node,
    stamp_seconds,
)
from n2d_dope.config import DetectConfig, RefineConfig
from n2d_dope.infer import Detection, DopeModel
from n2d_dope.nodes.scene_msgs import (
    collision_mesh,
    collision_object,
    collision_object_fields,
    marker_array,
    mesh_uri,
    moveit_modules,
)
from n2d_dope.track import TrackConfig, Tracker

MODELS_DOC = ("DOPE model directories (from `n2d train`), one per object: a string array, or one string of comma- "
              "or space-separated directories.")


@dataclass
class DopeNodeConfig:
    """Parameters of dope_node, besides `models` (a string or a string array, declared by the node itself)."""

    ROS_PARAMETERS = ("precision", "threads", "image_topic", "camera_info_topic", "camera_frame", "max_rate_hz",
                      "publish_overlay", "publish_tf", "tf_prefix", "publish_scene", "refine", "track",
                      "redetect_frames")
    """The user tier: these become ROS parameters; every other field is set in the `config_file` YAML."""

    precision: Literal["fp32", "int8"] = "fp32"
    """ONNX model of each directory to run: fp32, or int8 (statically quantised; faster on most CPUs)."""
    threads: int = 0
    """ONNX Runtime threads per model (0: all cores)."""
    image_topic: str = "camera/image_raw"
    """Camera images, undistorted (rgb8, bgr8, mono8, ...)."""
    camera_info_topic: str = "camera/camera_info"
    """Intrinsics of the images (K)."""
    camera_frame: str = ""
    """frame_id of the published poses; empty: the image header's."""
    max_rate_hz: float = 0.0
    """Process at most this many frames per second; 0: every frame the detector keeps up with."""
    publish_overlay: bool = True
    """Publish `dope/overlay`: the image with the detected cuboids and axes drawn."""
    publish_tf: bool = True
    """Broadcast each object's pose on /tf: camera frame -> `tf_prefix` + object name."""
    tf_prefix: str = "n2d/"
    """Prefix of the objects' TF frame names."""
    publish_scene: bool = True
    """Publish `dope/markers` (each object's mesh at its pose, for RViz) and, where moveit_msgs is installed,
    each object as a CollisionObject on /collision_object (MoveIt's planning scene)."""
    log_period_s: float = 10.0
    """Log frames received, frames processed and the latency this often (seconds); 0: never."""
    refine: bool = True
    """Refine each detected pose against the image with the object's model (region-based) and drop detections
    that do not fit it; needs the object's model directory the network was trained on."""
    track: bool = True
    """Follow each object from frame to frame by refinement (needs `refine`): the network runs in a worker of its
    own when no object is tracked and every `redetect_frames` frames, the published poses keep the camera's rate."""
    redetect_frames: int = 10
    """While tracking, run the network again every this many frames (0: only when the track is lost)."""
    detect: DetectConfig = field(default_factory=DetectConfig)
    """Turning the network's maps into poses."""

    def __post_init__(self):
        for name in ("threads", "max_rate_hz", "log_period_s", "redetect_frames"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")


def model_dirs(value: str | list[str]) -> list[str]:
    """The `models` parameter as a list: array entries as given, a string split at commas and whitespace."""
    items = re.split(r"[,\s]+", value) if isinstance(value, str) else value
    return [d for d in items if d]


def pose_topic(object_name: str) -> str:
    """`dope/pose_<object>`, with characters a topic name cannot hold replaced by `_`."""
    return "dope/pose_" + re.sub(r"\W", "_", object_name, flags=re.ASCII)


def pose_stamped(det: Detection, header: Header) -> PoseStamped:
    """The pose of a detection's object frame in the camera frame."""
    return PoseStamped(header=header, pose=pose_msg(det.T_cam_obj))


def detection3d(det: Detection, cuboid_m: np.ndarray, header: Header) -> Detection3D:
    """A detection as vision_msgs has it: the hypothesis (object, score, pose of the object frame) and the fitted
    cuboid as bounding box (pose of its centre, edge lengths). `cuboid_m`: the model's 9 x 3 keypoints, an
    axis-aligned box in the object frame (8 corners, then the centre)."""
    T_cam_box = det.T_cam_obj.copy()
    T_cam_box[:3, 3] = transform_points(det.T_cam_obj, cuboid_m[8:9])[0]
    sx, sy, sz = (float(v) for v in np.ptp(cuboid_m[:8], axis=0))
    hypothesis = ObjectHypothesisWithPose(hypothesis=ObjectHypothesis(class_id=det.object, score=float(det.score)),
                                          pose=PoseWithCovariance(pose=pose_msg(det.T_cam_obj)))
    return Detection3D(header=header, results=[hypothesis], id=f"{det.object}:{det.source}",
                       bbox=BoundingBox3D(center=pose_msg(T_cam_box), size=Vector3(x=sx, y=sy, z=sz)))


def transform_stamped(det: Detection, header: Header, child_frame: str) -> TransformStamped:
    """The object frame of a detection as a TF transform: header.frame_id (the camera) -> `child_frame`."""
    pose = pose_msg(det.T_cam_obj)
    return TransformStamped(header=header, child_frame_id=child_frame, transform=Transform(
        translation=Vector3(x=pose.position.x, y=pose.position.y, z=pose.position.z), rotation=pose.orientation))


def draw_overlay(rgb: np.ndarray, K: np.ndarray, detections: list[Detection],
                 cuboids: dict[str, np.ndarray]) -> np.ndarray:
    """A copy of `rgb` with each detection's fitted cuboid, object axes and label drawn."""
    out = rgb.copy()
    thickness = max(1, round(min(out.shape[:2]) / 240))
    for det in detections:
        cuboid = cuboids[det.object]
        corners = project(K, det.T_cam_obj, cuboid[:8])
        corners[transform_points(det.T_cam_obj, cuboid[:8])[:, 2] <= 0] = np.nan  # behind the camera
        draw_cuboid(out, corners, thickness=thickness)
        draw_axes(out, K, det.T_cam_obj, 0.5 * float(np.ptp(cuboid[:8], axis=0).max()), thickness)
        if np.isfinite(corners[0]).all():
            cv2.putText(out, f"{det.object} {det.score:.2f}", tuple(np.round(corners[0]).astype(int)),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.4 * thickness, (255, 255, 0), thickness, cv2.LINE_AA)
    return out


class DopeNode(Node):
    NAME = "dope"

    def __init__(self):
        super().__init__(self.NAME)
        models = self.declare_parameter("models", "", ParameterDescriptor(description=MODELS_DOC, dynamic_typing=True))
        self.cfg = declare_config(self, DopeNodeConfig)
        dirs = model_dirs(models.value)
        if not dirs:
            raise ConfigError("dope_node: no DOPE models given",
                              "set the parameter models, e.g. n2d launch dope models:=/path/to/dope_model")
        self.models = [self._load(d) for d in dirs]
        self.cuboids = {m.name: m.cuboid_m for m in self.models}
        if len(self.cuboids) < len(self.models):
            names = ", ".join(m.name for m in self.models)
            raise ConfigError(f"dope_node: two models detect the same object ({names})", "give one model per object")

        self.pose_pubs = {name: self.create_publisher(PoseStamped, pose_topic(name), PUBLISH_QOS)
                          for name in self.cuboids}
        self.detections_pub = self.create_publisher(Detection3DArray, "dope/detections", PUBLISH_QOS)
        self.latency_pub = self.create_publisher(Float64, "dope/latency_ms", PUBLISH_QOS)
        self.tf_pub = self.create_publisher(TFMessage, "/tf", TF_QOS) if self.cfg.publish_tf else None
        self.overlay_pub = (self.create_publisher(Image, "dope/overlay", PUBLISH_QOS) if self.cfg.publish_overlay
                            else None)
        self.object_dirs = self._object_dirs() if self.cfg.publish_scene else {}
        self.markers_pub = (self.create_publisher(MarkerArray, "dope/markers", PUBLISH_QOS) if self.cfg.publish_scene
                            else None)
        self.moveit = moveit_modules() if self.cfg.publish_scene else None
        self.collision_pub = (self.create_publisher(self.moveit[0].CollisionObject, "/collision_object", TF_QOS)
                              if self.moveit else None)
        self._in_scene: set[str] = set()

        self._new = threading.Condition()
        self._image: Image | None = None
        self._info: CameraInfo | None = None
        self._running = True
        self._received = 0
        self._latencies_ms: list[float] = []
        self.camera_info_sub = LiveSubscription(self, CameraInfo, self.cfg.camera_info_topic, self.on_camera_info)
        self.image_sub = LiveSubscription(self, Image, self.cfg.image_topic, self.on_image)
        self.trackers = {m.name: Tracker(m, TrackConfig(redetect_frames=self.cfg.redetect_frames))
                         for m in self.models if self.cfg.track and m.refiner is not None}
        self._tracked = threading.Lock()  # the trackers' state: the frame worker and the detection worker
        self._detect_job: tuple | None = None
        self._worker = threading.Thread(target=self._work, daemon=True)
        self._worker.start()
        self._detector = threading.Thread(target=self._detect_work, daemon=True)
        if self.trackers:
            self._detector.start()
        if self.cfg.log_period_s > 0:
            self._log_since = time.monotonic()
            self.create_timer(self.cfg.log_period_s, self.on_log_timer)
        mode = "tracking" if self.trackers else "refining" if any(m.refiner for m in self.models) else "detecting"
        self.get_logger().info(f"dope ready: {', '.join(self.cuboids)} ({self.cfg.precision}, {mode}) on "
                               f"{self.image_sub.topic_name}")

    def _load(self, directory: str) -> DopeModel:
        """A model, refining its detections when `refine` is set and its object's model can be found."""
        kwargs = dict(precision=self.cfg.precision, cfg=self.cfg.detect, threads=self.cfg.threads)
        if self.cfg.refine:
            try:
                return DopeModel(directory, refine=RefineConfig(), **kwargs)
            except ConfigError as exc:  # a network without its object's model still detects
                self.get_logger().warning(f"{directory}: no refinement or tracking: {exc.message} ({exc.hint})")
        return DopeModel(directory, **kwargs)

    def _object_dirs(self) -> dict[str, Path]:
        """Each object's model directory, for the markers and collision objects (objects without one are left out)."""
        out = {}
        for model in self.models:
            try:
                out[model.name] = model.object_dir()
            except ConfigError:
                self.get_logger().warning(f"{model.name}: no object model, so no marker or collision object")
        return out

    def publish_scene(self, best: list[Detection], header: Header) -> None:
        """The objects' mesh markers and, with MoveIt, their collision objects (added once with the mesh, then
        moved)."""
        self.markers_pub.publish(marker_array(best, header, {n: mesh_uri(d) for n, d in self.object_dirs.items()}))
        if self.collision_pub is None:
            return
        for det in best:
            if det.object in self.object_dirs:
                object_id = self.cfg.tf_prefix + det.object
                mesh = collision_mesh(self.object_dirs[det.object]) if object_id not in self._in_scene else None
                fields = collision_object_fields(det, header.frame_id, object_id, mesh)
                self.collision_pub.publish(collision_object(fields, header, self.moveit))
                self._in_scene.add(object_id)

    def on_image(self, msg: Image) -> None:
        with self._new:
            self._image = msg
            self._received += 1
            self._new.notify_all()

    def on_camera_info(self, msg: CameraInfo) -> None:
        with self._new:
            self._info = msg
            self._new.notify_all()

    def on_log_timer(self) -> None:
        with self._new:
            received, latencies, info = self._received, self._latencies_ms, self._info
            self._received, self._latencies_ms = 0, []
        now = time.monotonic()
        dt, self._log_since = now - self._log_since, now
        line = f"{received / dt:.1f} frames/s in, {len(latencies) / dt:.1f} processed"
        if latencies:
            line += f", latency {np.mean(latencies):.0f} ms mean, {np.max(latencies):.0f} ms max"
        if received and info is None:
            line += f"; no camera_info yet on {self.cfg.camera_info_topic}"
        self.get_logger().info(line)

    def _work(self) -> None:
        """Run the models on the newest frame, over and over, until the node is destroyed."""
        period_s = 1.0 / self.cfg.max_rate_hz if self.cfg.max_rate_hz > 0 else 0.0
        while True:
            with self._new:
                self._new.wait_for(lambda: not self._running or (self._image is not None and self._info is not None))
                if not self._running:
                    return
                image, info, self._image = self._image, self._info, None
            start = time.monotonic()
            try:
                self.process(image, info)
            except Exception as exc:  # one bad frame must not stop a live detector: say why and go on
                if not self.context.ok():
                    return
                self.get_logger().error(f"frame skipped: {exc}", throttle_duration_sec=5.0)
            with self._new:
                self._new.wait_for(lambda: not self._running, timeout=start + period_s - time.monotonic())

    def process(self, image: Image, info: CameraInfo) -> None:
        """Detect every object in one image and publish the results."""
        if info.width and (info.width, info.height) != (image.width, image.height):
            raise N2DError(f"camera_info is for {info.width}x{info.height} images, the image is "
                           f"{image.width}x{image.height}", "pair the image topic with its own camera_info")
        rgb = image_rgb(image)
        K = np.array(info.k, dtype=float).reshape(3, 3)
        header = Header(stamp=image.header.stamp, frame_id=self.cfg.camera_frame or image.header.frame_id)
        found = [det for model in self.models if model.name not in self.trackers for det in model.detect(rgb, K)]
        found += self._track(rgb, K, stamp_seconds(image.header.stamp))
        bests = []
        for name, pub in self.pose_pubs.items():
            best = max((det for det in found if det.object == name), key=lambda det: det.score, default=None)
            if best is not None:
                pub.publish(pose_stamped(best, header))
                bests.append(best)
        if self.tf_pub is not None and bests and header.frame_id:  # TF needs the camera's frame name
            self.tf_pub.publish(TFMessage(transforms=[transform_stamped(b, header, self.cfg.tf_prefix + b.object)
                                                      for b in bests]))
        if self.markers_pub is not None:
            self.publish_scene(bests, header)
        self.detections_pub.publish(Detection3DArray(
            header=header, detections=[detection3d(det, self.cuboids[det.object], header) for det in found]))
        latency_ms = (self.get_clock().now().nanoseconds * 1e-9 - stamp_seconds(image.header.stamp)) * 1e3
        self.latency_pub.publish(Float64(data=latency_ms))
        with self._new:
            self._latencies_ms.append(latency_ms)
        if self.overlay_pub is not None:
            self.overlay_pub.publish(image_msg(draw_overlay(rgb, K, found, self.cuboids), "rgb8", header.stamp,
                                               header.frame_id))

    def _track(self, rgb: np.ndarray, K: np.ndarray, stamp: float) -> list[Detection]:
        """Follow the tracked objects into this frame; hand the frame to the detection worker when one of them
        needs the network. Returns the poses as detections (score: the silhouette score)."""
        if not self.trackers:
            return []
        out = []
        with self._tracked:
            for name, tracker in self.trackers.items():
                pose = tracker.track(rgb, K, stamp)
                if pose is not None:
                    out.append(Detection(name, pose.T_cam_obj, pose.score, np.full((9, 2), np.nan), 0.0,
                                         pose.score, pose.source))
            due = any(t.needs_detection() for t in self.trackers.values())
        if due:
            with self._new:
                self._detect_job = (rgb, K, stamp)
                self._new.notify_all()
        return out

    def _detect_work(self) -> None:
        """Run the tracked objects' networks on the newest frame handed over, and offer the trackers the result."""
        while True:
            with self._new:
                self._new.wait_for(lambda: not self._running or self._detect_job is not None)
                if not self._running:
                    return
                (rgb, K, stamp), self._detect_job = self._detect_job, None
            try:
                for model in self.models:
                    tracker = self.trackers.get(model.name)
                    if tracker is not None:
                        found = model.detect(rgb, K)
                        with self._tracked:
                            tracker.offer(rgb, K, found, stamp)
            except Exception as exc:  # as in the frame worker: say why and go on
                if not self.context.ok():
                    return
                self.get_logger().error(f"detection skipped: {exc}", throttle_duration_sec=5.0)

    def destroy_node(self) -> None:
        with self._new:
            self._running = False
            self._new.notify_all()
        self._worker.join(timeout=10.0)
        if self._detector.is_alive():
            self._detector.join(timeout=10.0)
        super().destroy_node()


def main(args=None) -> None:
    run_node(DopeNode, args, threads=1)


if __name__ == "__main__":
    main()
