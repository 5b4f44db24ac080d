"""Capture faults end in one clear error and keep the views taken: a camera topic that goes silent
(real rclpy publisher and RosFrameSource), and a board that is in no view (real driver on the emulator)."""

import threading
import time

import numpy as np
import pytest
from sensor_msgs.msg import Image

from n2d_capture.board import CalibrationError
from n2d_capture.capture import CaptureConfig, capture
from n2d_capture.nodes.ros_io import RosFrameSource
from n2d_capture.sweep import SweepConfig, read_sweep
from n2d_capture.turntable import Turntable, TurntableConfig
from n2d_common.errors import DeviceError
from n2d_common.ros import PUBLISH_QOS, background_node, image_msg, stamp_msg


class Camera:
    """Publishes grey 64x48 frames on `topic` until `stop` is set (a camera driver that can go silent)."""

    def __init__(self, node, topic):
        self.pub = node.create_publisher(Image, topic, PUBLISH_QOS)
        self.stop = threading.Event()
        self.frames = 0
        threading.Thread(target=self._run, daemon=True).start()

    def _run(self):
        grey = np.full((48, 64, 3), 128, np.uint8)
        while not self.stop.is_set():
            self.pub.publish(image_msg(grey, "rgb8", stamp_msg(time.time()), "cam"))
            self.frames += 1
            time.sleep(0.05)


def _config(views):
    return CaptureConfig(sweep=SweepConfig(views=views, frame_timeout_s=2.0, first_frame_timeout_s=10.0),
                         intrinsics="calibrate")


def _table(sim):
    return Turntable(TurntableConfig(port=sim.link, velocity_limit_rad_s=6.0, acceleration_rad_s2=30.0,
                                     settle_time_s=0.02))


class SilentAfter:
    """The real RosFrameSource; the camera driver stops publishing after `n` views were taken."""

    def __init__(self, source, camera, n):
        self.source, self.camera, self.n, self.grabs = source, camera, n, 0

    def grab(self, after_s, timeout_s):
        if self.grabs == self.n + 1:  # +1: the sweep's first grab only waits for the camera to be up
            self.camera.stop.set()
            time.sleep(0.2)
        self.grabs += 1
        return self.source.grab(after_s, timeout_s)


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_silent_camera_and_missing_board(tmp_path, sim, ros_domain):
    session = tmp_path / "session"
    with background_node("test_camera", ros_domain) as node, _table(sim) as table:
        camera = Camera(node, "/test/image_raw")
        source = RosFrameSource(node, "/test/image_raw", "/test/camera_info")
        with pytest.raises(DeviceError, match="no fresh image on /test/image_raw"):
            capture(session, _config(4), table, SilentAfter(source, camera, 2))
        assert [v["index"] for v in read_sweep(tmp_path / "session.partial", "images")] == [0, 1]

        # the camera is back: the sweep resumes at view 2; no view shows the board, which is one clear error
        camera = Camera(node, "/test/image_raw")
        with pytest.raises(CalibrationError, match="board"):
            capture(session, _config(4), table, source)
        camera.stop.set()
    assert len(read_sweep(tmp_path / "session.partial", "images")) == 4
    assert not session.exists()
