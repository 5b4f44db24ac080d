"""Small helpers shared by the test files (import as `from helpers import ...`)."""

import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import cv2
import numpy as np

from n2d_common.ros import send_goal


def wait_future(future, timeout_s: float = 30.0, poll_s: float = 0.01):
    """The result of an rclpy future that a background executor completes; fails the test after `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while not future.done():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(poll_s)
    return future.result()


def send_and_cancel(client, request, when, timeout_s: float = 300.0):
    """Send an action goal and cancel it at the first feedback for which `when(feedback)` holds.

    Returns the goal handle and that feedback. The cancel is sent from the test's thread once the goal handle is
    known: feedback can arrive before the goal response, so a feedback callback cannot cancel by itself."""
    seen = []
    reached = threading.Event()

    def on_feedback(message):
        if not reached.is_set() and when(message.feedback):
            seen.append(message.feedback)
            reached.set()

    goal = send_goal(client, request, feedback_callback=on_feedback)
    assert goal.accepted
    assert reached.wait(timeout_s), "no matching feedback"
    wait_future(goal.cancel_goal_async(), 60)
    return goal, seen[0]


def write_photos(folder, images, suffix):
    """Save RGB images as a camera would name them: IMG_0000<suffix>, ... (JPEG at quality 95)."""
    folder.mkdir(parents=True, exist_ok=True)
    for i, rgb in enumerate(images):
        assert cv2.imwrite(str(folder / f"IMG_{i:04d}{suffix}"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR),
                           [cv2.IMWRITE_JPEG_QUALITY, 95])
    return folder


def look_at(eye, target) -> np.ndarray:
    """T_turntable_cam of an OpenCV camera (z forward, y down) at `eye` looking at `target` (Z up)."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
    T[:3, 3] = eye
    return T


ROS_OWN_PARAMETERS = {"use_sim_time", "start_type_description_service"}
"""Parameters rclpy declares on every node."""


def list_parameters(node, node_name: str, timeout_s: float = 30.0) -> list[str]:
    """The parameter names the node `node_name` (fully qualified) lists, as `ros2 param list` asks for them; `node`
    spins in another thread. rclpy's own parameters are left out."""
    from rcl_interfaces.srv import ListParameters

    client = node.create_client(ListParameters, f"{node_name}/list_parameters")
    try:
        assert client.wait_for_service(timeout_sec=timeout_s), f"{node_name} serves no list_parameters"
        result = wait_future(client.call_async(ListParameters.Request()), timeout_s).result
        return sorted(set(result.names) - ROS_OWN_PARAMETERS)
    finally:
        node.destroy_client(client)


RAY_START = ("import ray._private.services as s; s.resolve_ip_for_localhost = lambda host: host; "
             "from ray.scripts.scripts import main; main()")
"""`ray start` that keeps --node-ip-address=127.0.0.1 (Ray swaps loopback for the machine's address on a
multi-node cluster): every node on loopback only."""


def free_port() -> int:
    """A TCP port of loopback free now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class LocalCluster:
    """Ray nodes of this machine on loopback, each `ray start` in a process group of its own (so one node is
    killed without touching any other Ray of the machine), sharing a short temp dir."""

    def __init__(self):
        self.temp = tempfile.mkdtemp(prefix="n2dray", dir="/tmp")
        self.groups: dict[str, int] = {}
        self.port = 0

    def start(self, name: str, head: bool) -> None:
        args = [sys.executable, "-c", RAY_START, "start", "--node-ip-address=127.0.0.1", "--num-cpus=1",
                "--disable-usage-stats", f"--temp-dir={self.temp}"]
        if head:
            self.port = free_port()
            args += ["--head", f"--port={self.port}", "--include-dashboard=false",
                     f"--ray-client-server-port={free_port()}"]
        else:
            args += [f"--address=127.0.0.1:{self.port}"]
        log = Path(self.temp) / f"{name}.log"
        with log.open("w") as f:  # a file, not a pipe: the node's daemons keep it open
            proc = subprocess.Popen(args, start_new_session=True, stdout=f, stderr=f)
        self.groups[name] = proc.pid
        assert proc.wait(timeout=60) == 0, log.read_text()[-3000:]

    def kill(self, name: str) -> None:
        try:
            os.killpg(self.groups.pop(name), signal.SIGKILL)
        except ProcessLookupError:
            pass

    def stop(self) -> None:
        for name in list(self.groups):
            self.kill(name)
        shutil.rmtree(self.temp, ignore_errors=True)

    @property
    def address(self) -> str:
        return f"127.0.0.1:{self.port}"
