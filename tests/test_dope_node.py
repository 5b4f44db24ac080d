"""dope_node across processes: `n2d launch dope` with a tiny trained model, images + camera_info published from
here; overlay and detections per frame with the image's stamp and frame, stale frames dropped under a burst,
bounded latency, a best-effort camera driver matched too, clean exit on SIGINT. The message conversions are
checked on a hand-made detection."""

import json
import shutil
import signal
import time

import cv2
import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from helpers import list_parameters
from rclpy.qos import QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Float64, Header
from tf2_msgs.msg import TFMessage
from vision_msgs.msg import Detection3DArray
from visualization_msgs.msg import Marker, MarkerArray

from n2d.launch_description import load
from n2d.launcher import Launch
from n2d_common.frames import R_from_quat, make_T, quat_from_R, rot_z
from n2d_common.ros import (
    PUBLISH_QOS,
    SENSOR_QOS,
    background_node,
    camera_info_msg,
    image_msg,
    stamp_msg,
    stamp_seconds,
)
from n2d_dope.infer import Detection
from n2d_dope.nodes.dope_node import (
    detection3d,
    draw_overlay,
    model_dirs,
    pose_stamped,
    pose_topic,
    transform_stamped,
)

pytestmark = pytest.mark.slow  # real rendering, training or ROS round trips: tens of seconds or more

CUBOID = np.array([(1, 1, 1), (-1, 1, 1), (-1, -1, 1), (1, -1, 1), (1, 1, -1), (-1, 1, -1), (-1, -1, -1), (1, -1, -1),
                   (0, 0, 0)], dtype=float) * [0.04, 0.03, 0.07] + [0.0, 0.0, 0.01]
"""A 8 x 6 x 14 cm box whose centre sits 1 cm above the object origin (DOPE order: 8 corners, then the centre)."""
RATE_HZ = 5.0
"""The node's max_rate_hz."""


@pytest.fixture(scope="module")
def dope_model(tmp_path_factory):
    """A tiny DOPE model of the sample box trained on a two-frame dataset, and that dataset."""
    from n2d_common.config import load_config
    from n2d_dataset.config import DatasetConfig
    from n2d_dataset.generate import generate_dataset
    from n2d_dope.config import TrainConfig
    from n2d_dope.train import train
    from n2d_sim.objects import sample_object_dir

    tmp = tmp_path_factory.mktemp("dope")
    cfg = load_config(DatasetConfig, overrides=["frames=2", "camera.width=160", "camera.height=120",
                                                "camera.focal_px=150", "render.samples=2"])
    generate_dataset([sample_object_dir("box")], tmp / "ds", cfg)
    train(tmp / "ds", tmp / "dope", TrainConfig.preset("tiny"))
    return tmp / "dope", tmp / "ds"


def test_message_conversions():
    T = make_T(rot_z(np.pi / 2)[:3, :3], [0.1, -0.2, 0.5])
    det = Detection("box", T, 0.75, np.zeros((9, 2)), 1.5)
    header = Header(stamp=stamp_msg(12.5), frame_id="cam")

    pose = pose_stamped(det, header)
    assert pose.header.frame_id == "cam" and stamp_seconds(pose.header.stamp) == 12.5
    p, q = pose.pose.position, pose.pose.orientation
    assert np.allclose([p.x, p.y, p.z], [0.1, -0.2, 0.5])
    assert np.allclose([q.x, q.y, q.z, q.w], [0, 0, np.sqrt(0.5), np.sqrt(0.5)])

    d = detection3d(det, CUBOID, header)
    assert d.header.frame_id == "cam" and len(d.results) == 1 and d.id == "box:detected"
    hyp = d.results[0]
    assert hyp.hypothesis.class_id == "box" and hyp.hypothesis.score == 0.75
    assert hyp.pose.pose == pose.pose
    # the box centre is 1 cm along the object's z, which the pose keeps along the camera's z
    c = d.bbox.center
    assert np.allclose([c.position.x, c.position.y, c.position.z], [0.1, -0.2, 0.51])
    assert np.allclose([c.orientation.x, c.orientation.y, c.orientation.z, c.orientation.w], quat_from_R(T[:3, :3]))
    assert np.allclose([d.bbox.size.x, d.bbox.size.y, d.bbox.size.z], [0.08, 0.06, 0.14])

    K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])
    rgb = np.zeros((240, 320, 3), np.uint8)
    out = draw_overlay(rgb, K, [det], {"box": CUBOID})
    assert out.shape == rgb.shape and out.any() and not rgb.any()  # drawn on a copy
    assert draw_overlay(rgb, K, [], {"box": CUBOID}).sum() == 0

    assert model_dirs("/a/dope, /b/dope /c") == ["/a/dope", "/b/dope", "/c"]
    assert model_dirs(["/a b/dope", ""]) == ["/a b/dope"]
    assert pose_topic("sugar-box.2") == "dope/pose_sugar_box_2"

    tf = transform_stamped(det, header, "n2d/box")
    assert (tf.header.frame_id, tf.child_frame_id) == ("cam", "n2d/box")
    assert np.allclose(_transform_T(tf.transform), T, atol=1e-9)


def _transform_T(transform) -> np.ndarray:
    """4 x 4 of a geometry_msgs/Transform, as a TF listener composes it."""
    t, q = transform.translation, transform.rotation
    return make_T(R_from_quat([q.x, q.y, q.z, q.w]), [t.x, t.y, t.z])


def _pose_T(pose) -> np.ndarray:
    p, q = pose.position, pose.orientation
    return make_T(R_from_quat([q.x, q.y, q.z, q.w]), [p.x, p.y, p.z])


def _frames(dataset, scale: int = 1):
    """(rgb, K) of the dataset's frames, upscaled by `scale`."""
    chunk = dataset / "train_pbr" / "000000"
    cameras = json.loads((chunk / "scene_camera.json").read_text())
    out = []
    for image in sorted((chunk / "rgb").glob("*.jpg")):
        rgb = cv2.cvtColor(cv2.imread(str(image)), cv2.COLOR_BGR2RGB)
        K = np.array(cameras[str(int(image.stem))]["cam_K"]).reshape(3, 3)
        if scale != 1:
            rgb = cv2.resize(rgb, None, fx=scale, fy=scale, interpolation=cv2.INTER_LINEAR)
            K = np.diag([scale, scale, 1.0]) @ K
        out.append((rgb, K))
    return out


def _camera(node):
    """The test camera's image and camera_info publishers, and a QoS that keeps every message the test receives."""
    return (node.create_publisher(Image, "/n2d/camera/image_raw", PUBLISH_QOS),
            node.create_publisher(CameraInfo, "/n2d/camera/camera_info", PUBLISH_QOS),
            QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE))


def _low_thresholds(tmp_path):
    """The node's config file (expert settings are no parameters) with detection thresholds low enough that even
    the barely trained test model finds (meaningless) boxes."""
    path = tmp_path / "dope.yaml"
    path.write_text("detect: {peak_threshold: 0.01, min_keypoints: 4, min_inliers: 0, affinity_threshold: 3.2}\n")
    return path


def _wait(predicate, timeout_s: float, what: str, logs: list[str]):
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, f"timed out waiting for {what}:\n" + "\n".join(logs[-20:])
        time.sleep(0.02)


@pytest.mark.timeout(240)
def test_dope_node_live(dope_model, ros_domain, tmp_path):
    model_dir, dataset = dope_model
    box_size = np.ptp(json.loads((model_dir / "config.json").read_text())["cuboid_points_m"][:8], axis=0)
    logs: list[str] = []
    received = {"detections": [], "overlay": [], "latency": [], "pose": [], "tf": [], "markers": []}
    spec = load("dope")
    # low detection thresholds and no refinement (which would reject the meaningless boxes): the pose path runs
    spec.nodes[0].parameters["refine"] = False
    args = {"models": str(model_dir), "max_rate_hz": str(RATE_HZ), "config": str(_low_thresholds(tmp_path))}
    with Launch(spec, args, log=logs.append) as launch:
        with background_node("test_camera", ros_domain) as node:
            image_pub, info_pub, every = _camera(node)
            node.create_subscription(Detection3DArray, "/n2d/dope/detections", received["detections"].append, every)
            node.create_subscription(Image, "/n2d/dope/overlay", received["overlay"].append, every)
            node.create_subscription(Float64, "/n2d/dope/latency_ms", received["latency"].append, every)
            node.create_subscription(PoseStamped, "/n2d/dope/pose_box", received["pose"].append, every)
            node.create_subscription(TFMessage, "/tf", lambda m: received["tf"].extend(m.transforms), every)
            node.create_subscription(MarkerArray, "/n2d/dope/markers", received["markers"].append, every)
            _wait(lambda: image_pub.get_subscription_count() and node.count_publishers("/n2d/dope/overlay"), 60,
                  "dope_node", logs)

            # the detections' type, as DDS discovery reports it: vision_msgs' own name and hash
            from test_interop_msgs import upstream_hashes

            endpoint = node.get_publishers_info_by_topic("/n2d/dope/detections")[0]
            assert endpoint.topic_type == "vision_msgs/msg/Detection3DArray"
            expected = upstream_hashes(tmp_path, "vision_msgs")["Detection3DArray"]
            assert endpoint.topic_type_hash.version == 1
            assert "RIHS01_" + endpoint.topic_type_hash.value.hex() == expected

            def publish(rgb, K, stamp):
                info_pub.publish(camera_info_msg(K, rgb.shape[1], rgb.shape[0], stamp, "test_cam"))
                image_pub.publish(image_msg(rgb, "rgb8", stamp, "test_cam"))

            def with_stamp(msgs, t_s):
                return next((m for m in msgs if stamp_seconds(m.header.stamp) == t_s), None)

            # one frame at a time: each is processed, with the image's stamp, frame and size
            for rgb, K in _frames(dataset):
                stamp = stamp_msg(time.time())
                t = stamp_seconds(stamp)
                deadline = time.monotonic() + 30
                while with_stamp(received["detections"], t) is None:  # until discovery has matched both ways
                    assert time.monotonic() < deadline, "no detections:\n" + "\n".join(logs[-20:])
                    publish(rgb, K, stamp)
                    time.sleep(0.3)
                detections = with_stamp(received["detections"], t)
                assert detections.header.frame_id == "test_cam"
                if detections.detections:  # not asserted: an untrained model may find nothing
                    assert all(d.results[0].hypothesis.class_id == "box" for d in detections.detections)
                    assert all(np.allclose([d.bbox.size.x, d.bbox.size.y, d.bbox.size.z], box_size)
                               for d in detections.detections)
                    best = max(detections.detections, key=lambda d: d.results[0].hypothesis.score)
                    _wait(lambda t=t: with_stamp(received["pose"], t) is not None, 10, "the pose", logs)
                    assert with_stamp(received["pose"], t).pose == best.results[0].pose.pose
                    assert best.id == "box:detected"
                    # on /tf: the camera frame -> n2d/box, the same pose as a listener composes it
                    _wait(lambda t=t: with_stamp(received["tf"], t) is not None, 10, "the transform", logs)
                    tf = with_stamp(received["tf"], t)
                    assert (tf.header.frame_id, tf.child_frame_id) == ("test_cam", "n2d/box")
                    assert np.allclose(_transform_T(tf.transform), _pose_T(best.results[0].pose.pose), atol=1e-6)
                    # for RViz: the object's mesh at the same pose
                    _wait(lambda t=t: any(stamp_seconds(m.markers[0].header.stamp) == t for m in received["markers"]),
                          10, "the markers", logs)
                    marker = next(m for m in received["markers"]
                                  if stamp_seconds(m.markers[0].header.stamp) == t).markers[1]
                    assert marker.type == Marker.MESH_RESOURCE and marker.pose == best.results[0].pose.pose
                _wait(lambda t=t: with_stamp(received["overlay"], t) is not None, 10, "the overlay", logs)
                overlay = with_stamp(received["overlay"], t)
                assert (overlay.width, overlay.height, overlay.encoding) == (rgb.shape[1], rgb.shape[0], "rgb8")
                assert overlay.header.frame_id == "test_cam"

            # a burst much faster than max_rate_hz: the node drops stale frames rather than queueing them
            burst = [(image_msg(rgb, "rgb8", stamp_msg(0), "test_cam"),
                      camera_info_msg(K, rgb.shape[1], rgb.shape[0], stamp_msg(0), "test_cam"))
                     for rgb, K in _frames(dataset, scale=4)] * 20
            for _ in range(5):  # the burst's camera_info first
                info_pub.publish(burst[0][1])
                time.sleep(0.2)  # and repeats of the last single frame drain meanwhile
            for msgs in received.values():
                msgs.clear()
            sent = []
            for image, info in burst:
                info.header.stamp = image.header.stamp = stamp_msg(time.time())
                sent.append(stamp_seconds(image.header.stamp))
                info_pub.publish(info)
                image_pub.publish(image)
            _wait(lambda: received["detections"], 20, "detections of the burst", logs)
            time.sleep(2.0)  # a node that queued the burst would still be publishing now
            processed = [sent.index(stamp_seconds(d.header.stamp)) for d in received["detections"]]
            # after a frame the node waits 1 / RATE_HZ, then takes the newest that arrived (which ones it gets
            # varies with the timing)
            assert len(processed) <= len(sent) // 4, (processed, len(sent))
            latencies = [m.data for m in received["latency"]]
            assert latencies and max(latencies) < 5000 / RATE_HZ, latencies  # a backlog: len(sent) / RATE_HZ s

            # a camera driver publishing best effort (sensor-data QoS), which the node's reliable subscription
            # cannot match: the node re-subscribes best effort and processes its frames too
            best_effort_pub = node.create_publisher(Image, "/n2d/camera/image_raw", SENSOR_QOS)
            rgb, K = _frames(dataset)[0]
            stamp = stamp_msg(time.time())
            deadline = time.monotonic() + 30
            while with_stamp(received["detections"], stamp_seconds(stamp)) is None:
                assert time.monotonic() < deadline, "nothing from the best-effort publisher:\n" + "\n".join(logs)
                info_pub.publish(camera_info_msg(K, rgb.shape[1], rgb.shape[0], stamp, "test_cam"))
                best_effort_pub.publish(image_msg(rgb, "rgb8", stamp, "test_cam"))
                time.sleep(0.3)
            assert any("subscribed best effort" in line for line in logs), logs[-20:]
            assert not launch.dead(), logs[-20:]

        proc = launch.procs["dope"]
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=15) == 0, logs[-20:]
    assert not any("Traceback" in line or "ERROR" in line for line in logs), "\n".join(logs)


@pytest.mark.timeout(240)
def test_dope_node_refines_and_tracks_by_default(dope_model, ros_domain, tmp_path):
    """With the defaults the node loads the object's model kept in the DOPE directory, runs the network in its
    detection worker and publishes one (refined or tracked) result per frame; a model directory whose object
    model is gone still detects, with a warning."""
    model_dir, dataset = dope_model
    assert (model_dir / "object" / "mesh.obj").is_file() and (model_dir / "region_model.npz").is_file()
    logs: list[str] = []
    received = []
    markers = []
    spec = load("dope")
    args = {"models": str(model_dir), "max_rate_hz": str(RATE_HZ), "config": str(_low_thresholds(tmp_path))}
    with Launch(spec, args, log=logs.append) as launch:
        with background_node("test_camera", ros_domain) as node:
            image_pub, info_pub, every = _camera(node)
            node.create_subscription(Detection3DArray, "/n2d/dope/detections", received.append, every)
            node.create_subscription(MarkerArray, "/n2d/dope/markers", markers.append, every)
            _wait(lambda: image_pub.get_subscription_count(), 60, "dope_node", logs)
            assert any("box (fp32, tracking)" in line for line in logs), logs[-10:]
            listed = list_parameters(node, "/n2d/dope")
            assert "config_file" in listed and "detect.peak_threshold" not in listed and len(listed) <= 15, listed
            stamps = []
            for rgb, K in _frames(dataset) * 3:
                stamp = stamp_msg(time.time())
                stamps.append(stamp_seconds(stamp))
                deadline = time.monotonic() + 30
                while stamps[-1] not in [stamp_seconds(m.header.stamp) for m in received]:
                    assert time.monotonic() < deadline, "no result for a frame:\n" + "\n".join(logs[-20:])
                    info_pub.publish(camera_info_msg(K, rgb.shape[1], rgb.shape[0], stamp, "test_cam"))
                    image_pub.publish(image_msg(rgb, "rgb8", stamp, "test_cam"))
                    time.sleep(0.3)
            for msg in received:
                assert all(d.id in ("box:detected", "box:tracked") for d in msg.detections)
                assert all(0.0 <= d.results[0].hypothesis.score <= 1.0 for d in msg.detections)
            _wait(lambda: len(markers) >= len(stamps), 30, "a marker array per frame", logs)
            # each frame clears the old markers; a found object gets the mesh of the model it was trained on
            assert all(m.markers[0].action == Marker.DELETEALL for m in markers)
            meshes = [k for m in markers for k in m.markers[1:]]  # none when the refinement drops every box
            assert all(k.type == Marker.MESH_RESOURCE and k.ns == "box" for k in meshes)
            assert all(k.mesh_resource == (model_dir / "object" / "mesh.obj").resolve().as_uri() for k in meshes)
            assert not launch.dead(), logs[-20:]
    assert not any("Traceback" in line or "skipped" in line for line in logs), "\n".join(logs)

    # the same network without its object's model (moved without it): it detects, and says why it cannot refine
    bare = tmp_path / "dope"
    shutil.copytree(model_dir, bare, ignore=shutil.ignore_patterns("object", "region_model.npz"))
    config = json.loads((bare / "config.json").read_text())
    config.pop("object_model")
    config["model_dir"] = str(tmp_path / "gone")
    (bare / "config.json").write_text(json.dumps(config))
    logs.clear()
    with Launch(spec, {"models": str(bare)}, log=logs.append) as launch:
        _wait(lambda: any("dope ready" in line for line in logs) or launch.dead(), 60, "dope_node", logs)
        assert any("box (fp32, detecting)" in line for line in logs), logs[-10:]
        assert any("no refinement or tracking" in line and "no object model" in line for line in logs), logs[-10:]
