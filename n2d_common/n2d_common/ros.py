"""The ROS 2 helpers every n2d node shares: environment, config <-> parameters, image/pose messages, main().

Only node modules import this; the stage libraries stay free of ROS.
"""

from __future__ import annotations

import array
import contextlib
import os
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import rclpy
from action_msgs.msg import GoalStatus
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Pose, Transform, Vector3
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.action import ActionClient, ActionServer, CancelResponse, GoalResponse
from rclpy.action.client import ClientGoalHandle
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation
from rclpy.lifecycle import LifecycleNodeMixin
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import CameraInfo, Image
from unique_identifier_msgs.msg import UUID

from n2d_common.config import flat_fields, from_dict, merge, read_mapping, to_dict
from n2d_common.errors import Cancelled, ConfigError, DeviceError, N2DError
from n2d_common.frames import quat_from_R

C = TypeVar("C")
FASTDDS_PROFILE = Path(__file__).with_name("fastdds_localhost.xml")

SENSOR_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.BEST_EFFORT,
                        durability=DurabilityPolicy.VOLATILE)
"""Subscribing to small live state (joint states, poses): keep only the newest message, never queue stale ones."""
LIVE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.VOLATILE)
"""Subscribing to live video (`LiveSubscription`): keep only the newest frame, so a slow subscriber drops stale
frames instead of queueing them; reliable, because best effort loses most large frames with Fast DDS even on one
host (640x480 rgb8 at 30 Hz: 6-12 of 30 frames/s arrive best effort, all 30 reliable; measured on this project's
2-core machine, with and without n2d's shared-memory profile)."""
PUBLISH_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.VOLATILE)
"""Publishing frames and state: keep the newest only; reliable, so best-effort and reliable subscribers both match."""
TF_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.VOLATILE)
"""/tf as tf2's TransformBroadcaster publishes it."""
TF_STATIC_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
"""/tf_static as tf2's StaticTransformBroadcaster publishes it: latched, so late subscribers get it."""


def ros_environment(domain_id: int | None = None, env: dict | None = None) -> dict:
    """Environment defaults for ROS processes: localhost-only discovery, a log dir, shared-memory transport.

    Fills `env` (default: os.environ) in place where unset and returns it. Nothing leaves the machine.
    """
    env = os.environ if env is None else env
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    env.setdefault("HOME", "/tmp")
    env.setdefault("FASTDDS_DEFAULT_PROFILES_FILE", str(FASTDDS_PROFILE))
    if domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(domain_id)
    return env


def _param_value(value: Any) -> Any:
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, tuple):
        return list(value)
    return value


CONFIG_FILE_DOC = ("YAML file of the node's settings, the expert ones included: a mapping laid out as the parameter "
                   "names (`reconstruct: {neus: {steps: 2000}}`, or dotted keys), or a ROS 2 parameters file "
                   "(`node_name: {ros__parameters: {...}}`); the node's parameters override it.")


def user_parameters(cls: type) -> list[str]:
    """The dotted names of config `cls` that become ROS parameters: its `ROS_PARAMETERS` (the user tier), or
    every field of a config that names none."""
    names = [name for name, *_ in flat_fields(cls)]
    tier = getattr(cls, "ROS_PARAMETERS", None)
    if tier is None:
        return names
    unknown = sorted(set(tier) - set(names))
    if unknown:
        raise ValueError(f"{cls.__name__}.ROS_PARAMETERS names no field: {', '.join(unknown)}")
    return list(tier)


def _unflatten(data: dict) -> dict:
    """A mapping with dotted keys (`a.b: 1`, at any depth) as nested sections (`a: {b: 1}`)."""
    out: dict = {}
    for key, value in data.items():
        *sections, leaf = str(key).split(".")
        node = out
        for section in sections:
            node = node.setdefault(section, {})
        value = _unflatten(value) if isinstance(value, dict) else value
        node[leaf] = merge(node[leaf], value) if isinstance(value, dict) and isinstance(node.get(leaf), dict) \
            else value
    return out


def read_node_config(cls: type[C], path: str) -> C:
    """Config `cls` from the defaults and the YAML file at `path` (see CONFIG_FILE_DOC); ConfigError naming the
    file when it cannot be read or holds a bad value."""
    data = read_mapping(path)
    if len(data) == 1:  # a ROS 2 parameters file: {node_name: {ros__parameters: {...}}}, node name or /**
        (section,) = data.values()
        if isinstance(section, dict) and "ros__parameters" in section:
            data = section["ros__parameters"] or {}
    try:
        return from_dict(cls, merge(to_dict(cls()), _unflatten(data)))
    except ConfigError as exc:
        raise ConfigError(f"config_file {path}: {exc.message}", exc.hint) from None


def declare_config(node: Node, cls: type[C]) -> C:
    """Declare the user tier of config `cls` as parameters (dotted names, the field docstring as description,
    read-only: the node reads them once) and `config_file`, and return the config: defaults, then the config
    file, then the parameters. An expert setting given as a parameter or a bad value raises ConfigError naming
    it."""
    path = node.declare_parameter("config_file", "", ParameterDescriptor(description=CONFIG_FILE_DOC,
                                                                         read_only=True)).value
    base = read_node_config(cls, path) if path else cls()
    tier = set(user_parameters(cls))
    given = set(getattr(node, "_parameter_overrides", {}))  # rclpy keeps the --ros-args -p values there
    expert = sorted(name for name, *_ in flat_fields(cls) if name in given and name not in tier)
    if expert:
        raise ConfigError(f"{', '.join(expert)}: expert setting(s), not parameters of {node.get_name()}",
                          "set them in the YAML file given as the config_file parameter (docs/ros.md)")
    data = to_dict(base)
    for name, _tp, _default, doc in flat_fields(cls):
        if name not in tier:
            continue
        *sections, leaf = name.split(".")
        section = data
        for part in sections:
            section = section[part]
        value = _param_value(section[leaf])
        if value is None or isinstance(value, dict) or (isinstance(value, list) and not value):
            continue  # ROS parameters cannot be None, mappings or untyped empty lists: keep the config's value
        # A float parameter given as a whole number (`rate_hz:=5` from a launch file) arrives as an integer,
        # which rclpy refuses for a float parameter; let those through and have from_dict convert them.
        floats = isinstance(value, float) or (isinstance(value, list) and any(isinstance(v, float) for v in value))
        descriptor = ParameterDescriptor(description=doc, dynamic_typing=floats, read_only=True)
        section[leaf] = node.declare_parameter(name, value, descriptor).value
    try:
        return from_dict(cls, data)
    except ConfigError as exc:
        raise ConfigError(f"parameter {exc.message}", exc.hint) from None


CANCEL_TRANSITION_S = 5.0
"""How long a job stopped by a cancel request waits for rclpy to mark its goal as cancelling."""


def _await_cancel_transition(goal_handle) -> None:
    """Wait until `goal_handle` is CANCELING. rclpy calls the cancel callback (which sets the job's cancel event)
    before it moves the goal to CANCELING; a job that stops in between would end an EXECUTING goal as canceled, an
    invalid transition that leaves the client without a result."""
    deadline = time.monotonic() + CANCEL_TRANSITION_S
    while not goal_handle.is_cancel_requested and time.monotonic() < deadline:
        time.sleep(0.005)


class JobActionServer:
    """An action server that runs one long job at a time, shared by the stage nodes.

    A goal is refused while a job runs or when `accept(goal)` is false. `run(goal, result, progress, cancel)`
    does the work and fills the result; its Progress reports become feedback through `feedback(progress)`, and
    a cancel request sets its `cancel` event. The goal ends succeeded (result.success) when `run` returns,
    canceled on Cancelled, aborted on N2DError or ValueError (logged); result.message holds the reason.
    `start(goal)` runs a job without an action client (for planners that only speak services); `state`,
    `progress` and `result` say where the current or last job stands.
    """

    def __init__(self, node: Node, action_type, name: str, run: Callable, *, accept: Callable[[Any], bool],
                 feedback: Callable[[Any], Any]):
        self.cancel = threading.Event()
        """Set by a cancel request (and on shutdown); jobs watch it."""
        self.state = "idle"
        """idle, running, succeeded, failed or cancelled."""
        self.progress: Any = None
        """The current or last job's last Progress report."""
        self.result: Any = None
        """The last finished job's result."""
        self._busy = threading.Lock()
        self._cancel_requested = False
        self._node, self._type, self._run, self._accept, self._feedback = node, action_type, run, accept, feedback
        self._server = ActionServer(node, action_type, name, execute_callback=self._execute,
                                    goal_callback=self._on_goal, cancel_callback=self._on_cancel,
                                    callback_group=ReentrantCallbackGroup())

    def _on_goal(self, goal):
        return GoalResponse.ACCEPT if self._accept(goal) and not self._busy.locked() else GoalResponse.REJECT

    def _on_cancel(self, _goal_handle):
        self._cancel_requested = True
        self.cancel.set()
        return CancelResponse.ACCEPT

    def _execute(self, goal_handle):
        if not self._busy.acquire(blocking=False):  # two goals accepted at once: never run a job twice
            goal_handle.abort()
            return self._type.Result(message="another job is running")
        try:
            self.cancel.clear()
            self._cancel_requested = False
            if goal_handle.is_cancel_requested:  # cancelled between its acceptance and now
                self.cancel.set()
            result = self._job(goal_handle.request, goal_handle.publish_feedback)
            state = self.state
            if state == "cancelled":
                if self._cancel_requested:
                    _await_cancel_transition(goal_handle)
                if not goal_handle.is_cancel_requested:  # stopped by shutdown, not by a cancel request
                    state = "failed"
            end = {"succeeded": goal_handle.succeed, "cancelled": goal_handle.canceled}.get(state, goal_handle.abort)
        finally:
            self._busy.release()
        end()
        return result

    def _job(self, goal, publish: Callable[[Any], None]):
        result = self._type.Result()
        self.state, self.progress, self.result = "running", None, None

        def report(p) -> None:
            self.progress = p
            publish(self._feedback(p))

        try:
            self._run(goal, result, report, self.cancel)
            result.success = True
            self.state = "succeeded"
        except Cancelled as exc:
            result.message = str(exc)
            self.state = "cancelled"
        except (N2DError, ValueError) as exc:
            result.message = str(exc)
            self._node.get_logger().error(result.message)
            self.state = "failed"
        self.result = result
        return result

    def start(self, goal) -> str:
        """Run `goal` in a thread of its own, without an action client; returns "" when it started, else why not."""
        if not self._accept(goal):
            return "the goal is incomplete"
        if not self._busy.acquire(blocking=False):
            return "another job is running"
        self.cancel.clear()
        self.state = "running"

        def job() -> None:
            try:
                self._job(goal, lambda _feedback: None)
            finally:
                self._busy.release()

        threading.Thread(target=job, daemon=True).start()
        return ""

    def destroy(self) -> None:
        """Tell a running job to stop and remove the server."""
        self.cancel.set()
        self._server.destroy()


def stamp_msg(t_s: float) -> Time:
    """builtin_interfaces/Time from seconds."""
    sec = int(t_s)
    return Time(sec=sec, nanosec=int(round((t_s - sec) * 1e9)) % 1_000_000_000)


def stamp_seconds(stamp: Time) -> float:
    """Seconds of a builtin_interfaces/Time."""
    return stamp.sec + stamp.nanosec * 1e-9


_CHANNELS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "8UC1": 1, "8UC3": 3}


def image_msg(pixels: np.ndarray, encoding: str, stamp: Time, frame_id: str) -> Image:
    """sensor_msgs/Image of a uint8 HxW or HxWxC array (no cv_bridge: it is not installable here)."""
    if encoding not in _CHANNELS or pixels.dtype != np.uint8:
        raise ValueError(f"image_msg: unsupported encoding/dtype {encoding}/{pixels.dtype}")
    pixels = np.ascontiguousarray(pixels)
    msg = Image()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.height, msg.width = pixels.shape[:2]
    msg.encoding = encoding
    msg.step = msg.width * _CHANNELS[encoding]
    msg.data = array.array("B", pixels.tobytes())
    return msg


def image_rgb(msg: Image) -> np.ndarray:
    """HxWx3 uint8 RGB from a sensor_msgs/Image in rgb8, bgr8, rgba8, bgra8 or mono8."""
    if msg.encoding not in _CHANNELS:
        raise N2DError(f"image encoding {msg.encoding!r} is not supported",
                       f"publish one of {', '.join(_CHANNELS)} (e.g. set the camera driver to rgb8)")
    c = _CHANNELS[msg.encoding]
    rows = np.frombuffer(msg.data, np.uint8).reshape(msg.height, msg.step)
    px = rows[:, : msg.width * c].reshape(msg.height, msg.width, c)
    if c == 1:
        return np.repeat(px, 3, axis=2)
    if msg.encoding.startswith("bgr"):
        px = px[..., 2::-1]
    return np.ascontiguousarray(px[..., :3])


def camera_info_msg(K: np.ndarray, width: int, height: int, stamp: Time, frame_id: str) -> CameraInfo:
    """sensor_msgs/CameraInfo of an undistorted pinhole camera with intrinsics K."""
    msg = CameraInfo()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.width, msg.height = int(width), int(height)
    msg.distortion_model = "plumb_bob"
    msg.d = [0.0] * 5
    msg.k = [float(v) for v in np.asarray(K, dtype=float).reshape(9)]
    msg.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    P = np.zeros((3, 4))
    P[:, :3] = K
    msg.p = [float(v) for v in P.reshape(12)]
    return msg


def pose_msg(T: np.ndarray) -> Pose:
    """geometry_msgs/Pose of a 4x4 transform."""
    pose = Pose()
    pose.position.x, pose.position.y, pose.position.z = (float(v) for v in T[:3, 3])
    q = quat_from_R(T[:3, :3])
    pose.orientation.x, pose.orientation.y, pose.orientation.z, pose.orientation.w = (float(v) for v in q)
    return pose


def transform_msg(T: np.ndarray) -> Transform:
    """geometry_msgs/Transform of a 4x4 transform."""
    pose = pose_msg(T)
    return Transform(translation=Vector3(x=pose.position.x, y=pose.position.y, z=pose.position.z),
                     rotation=pose.orientation)


class LiveSubscription:
    """A subscription to a live stream (camera images and their CameraInfo) with `LIVE_QOS`.

    A reliable subscription cannot match a best-effort publisher (some camera drivers publish sensor-data QoS):
    when one shows up, this re-subscribes best effort, which matches every publisher, and says so in the log.
    """

    def __init__(self, node: Node, msg_type: type, topic: str, callback: Callable[[Any], None]):
        self._node, self._msg_type, self._callback = node, msg_type, callback
        self._fallback_timer = None
        events = SubscriptionEventCallbacks(incompatible_qos=self._on_incompatible_qos)
        self.subscription = node.create_subscription(msg_type, topic, callback, LIVE_QOS, event_callbacks=events)
        self.topic_name = self.subscription.topic_name

    def _on_incompatible_qos(self, _event) -> None:
        if self._fallback_timer is None and self.subscription is not None:
            # Not here: a subscription is not replaced from inside its own event callback.
            self._fallback_timer = self._node.create_timer(0.0, self._subscribe_best_effort)

    def _subscribe_best_effort(self) -> None:
        self._node.destroy_timer(self._fallback_timer)
        if self.subscription is None:
            return
        self._node.destroy_subscription(self.subscription)
        self.subscription = self._node.create_subscription(self._msg_type, self.topic_name, self._callback,
                                                           SENSOR_QOS)
        self._node.get_logger().info(f"{self.topic_name}: a best-effort publisher; subscribed best effort")

    def destroy(self) -> None:
        """Unsubscribe."""
        if self.subscription is not None:
            self._node.destroy_subscription(self.subscription)
            self.subscription = None


def refuse_invalid_transitions(node: LifecycleNodeMixin) -> None:
    """Have a lifecycle node answer `success: false` to a transition its state does not have.

    rclpy's `change_state` service raises on one (e.g. configure while finalized, `ros2 lifecycle set` with a
    wrong label), which ends the executor's spin and with it the node process; rclcpp answers false.
    """
    service = getattr(node, "_service_change_state", None)
    if service is None:  # enable_communication_interface=False: no services
        return
    change = service.callback

    def guarded(request, response):
        try:
            return change(request, response)
        except rclpy_implementation.RCLError as exc:
            node.get_logger().warning(f"lifecycle transition {request.transition.id} "
                                      f"{request.transition.label!r} refused: {str(exc).splitlines()[0]}")
            response.success = False
            return response

    service.callback = guarded


def run_node(node_cls: type[Node], args: list[str] | None = None, threads: int = 4) -> None:
    """The `main()` of every n2d node: init, spin on an executor with `threads` threads, clean shutdown.

    A configuration or device error at start-up is logged as one line and exits non-zero.
    """
    ros_environment()
    rclpy.init(args=args)
    node = None
    code = 0
    try:
        node = node_cls()
        executor = SingleThreadedExecutor() if threads == 1 else MultiThreadedExecutor(num_threads=threads)
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except N2DError as exc:
        name = getattr(node_cls, "NAME", node_cls.__name__)
        rclpy.logging.get_logger(name).fatal(str(exc))
        code = 2
    finally:
        if node is not None:
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
    if code:
        raise SystemExit(code)


RCLPY_SERIALISES_ACTION_REQUESTS = "_lock" in ActionClient.__init__.__code__.co_names
"""Whether the installed rclpy has the fix of ros2/rclpy#1123 (PR #1308, backported to Jazzy in #1519): its
ActionClient holds a lock around sending a request and handling the response."""


class SafeActionClient(ActionClient):
    """rclpy's ActionClient, safe to call from a thread other than the executor's, and recording the goal status
    the server publishes.

    rclpy releases without the fix of ros2/rclpy#1123 (Jazzy's 7.1.5 among them) register a request's future only
    after sending the request; when the executor thread handles the response in between, it is dropped
    ("Ignoring unexpected goal response") and the future never completes. With such an rclpy, sending and
    handling are serialised here; with a fixed one, rclpy's own lock does it.
    """

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._request_lock = contextlib.nullcontext() if RCLPY_SERIALISES_ACTION_REQUESTS else threading.RLock()
        self.server_goals: dict[bytes, int] = {}
        """The last status the server published for each goal id it knows (GoalStatus.STATUS_*)."""

    def send_goal_async(self, *args, **kwargs):
        with self._request_lock:
            return super().send_goal_async(*args, **kwargs)

    def _cancel_goal_async(self, goal_handle):
        with self._request_lock:
            return super()._cancel_goal_async(goal_handle)

    def _get_result_async(self, goal_handle):
        with self._request_lock:
            return super()._get_result_async(goal_handle)

    async def execute(self, taken_data):
        with self._request_lock:
            if "status" in taken_data:
                for status in taken_data["status"].status_list:
                    self.server_goals[bytes(status.goal_info.goal_id.uuid)] = status.status
            return await super().execute(taken_data)


def wait_future(future, timeout_s: float, what: str):
    """The result of an rclpy future completed by another thread's executor; DeviceError after `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while not future.done():
        if time.monotonic() > deadline:
            raise DeviceError(f"{what}: no answer within {timeout_s:.0f} s", "is the node serving it running?")
        time.sleep(0.01)
    return future.result()


def send_goal(client: ActionClient, goal, *, what: str = "action",
              feedback_callback: Callable[[Any], None] | None = None, attempts: int = 3, answer_s: float = 10.0):
    """Send `goal` on `client` (its node spinning in another thread); the server's answer, a ClientGoalHandle.

    Fast DDS waits only 100 ms for a service's reply writer to match the client's reader; right after
    discovery on a loaded machine it drops the goal response. Mostly the server notices ("Failed to send goal
    response") and never runs that goal, so a goal without an answer in `answer_s` is sent again under a new
    goal id, up to `attempts` times, and the first answer to come back is used. DeviceError when none does.
    A slow answer is not a lost one (a request that arrives before discovery is re-sent at the next
    heartbeat, seconds later), hence the long `answer_s`. Sometimes the response is lost without the server
    noticing and the goal runs: a SafeActionClient sees it in the server's goal status, and that goal is
    used as soon as it shows there (so it can be cancelled at once), rather than sending the job again.
    """
    pending = []
    taken = getattr(client, "server_goals", {})
    for _ in range(attempts):
        goal_id = UUID(uuid=list(uuid.uuid4().bytes))
        pending.append((goal_id, client.send_goal_async(goal, feedback_callback=feedback_callback, goal_uuid=goal_id)))
        deadline = time.monotonic() + answer_s
        while time.monotonic() < deadline:
            for goal_id, future in pending:
                if future.done():
                    return future.result()
                if bytes(goal_id.uuid) in taken:
                    accepted = client._action_type.Impl.SendGoalService.Response(accepted=True)
                    return ClientGoalHandle(client, goal_id, accepted)
            time.sleep(0.01)
    raise DeviceError(f"{what} goal: no answer from {client._action_name} within {attempts * answer_s:.0f} s",
                      "is the node serving it running?")


def call_action(client: ActionClient, goal, *, what: str, feedback: Callable[[Any], None] | None = None,
                cancel: threading.Event | None = None, server_timeout_s: float = 30.0,
                timeout_s: float | None = None):
    """Send `goal` on `client` (a SafeActionClient, its node spinning in another thread) and return the result.

    Each feedback message goes to `feedback`; setting `cancel` cancels the goal and raises Cancelled once
    the server has stopped. A refused goal, or one that ends aborted or with `success` false, raises
    N2DError with the server's message; DeviceError when the server is missing or `timeout_s` passes.
    """
    name = client._action_name
    if not client.wait_for_server(timeout_sec=server_timeout_s):
        raise DeviceError(f"{what}: the action {name} is not available", "start the node that serves it")
    on_feedback = (lambda msg: feedback(msg.feedback)) if feedback else None
    handle = send_goal(client, goal, what=what, feedback_callback=on_feedback)
    if not handle.accepted:
        raise N2DError(f"{what}: {name} refused the goal", "is it busy with another goal?")
    result_future = handle.get_result_async()
    deadline = None if timeout_s is None else time.monotonic() + timeout_s
    while not result_future.done():
        if cancel is not None and cancel.is_set():
            wait_future(handle.cancel_goal_async(), 10.0, f"cancelling {what}")
            wait_future(result_future, 120.0, f"cancelled {what}")
            raise Cancelled(f"{what} cancelled", "run it again to resume")
        if deadline is not None and time.monotonic() > deadline:
            raise DeviceError(f"{what} did not finish in {timeout_s:.0f} s")
        time.sleep(0.01)
    response = result_future.result()
    result = response.result
    if response.status == GoalStatus.STATUS_CANCELED:
        raise Cancelled(f"{what} was cancelled by another client", "run it again to resume")
    if response.status != GoalStatus.STATUS_SUCCEEDED or not getattr(result, "success", True):
        raise N2DError(f"{what}: {result.message or 'failed'}")
    return result


@contextmanager
def background_node(name: str, domain_id: int | None = None) -> Iterator[Node]:
    """For clients outside a node process (CLI, planners, tests): rclpy initialised, one node spinning in
    a background thread; executor, node and rclpy are shut down on exit."""
    ros_environment()
    # No rclpy signal handlers: Ctrl-C stays a KeyboardInterrupt of the caller's main thread, which then leaves
    # this context in order (rclpy's handler would shut the context down under the spinning thread).
    rclpy.init(domain_id=domain_id, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node(name)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    threading.Thread(target=executor.spin, daemon=True).start()
    try:
        yield node
    finally:
        executor.shutdown(timeout_sec=5.0)
        node.destroy_node()
        rclpy.shutdown()
