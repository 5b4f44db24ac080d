"""A whole capture session from the simulator through the real driver: empty-plate sweep, object sweep,
board poses + fitted turntable frame, masks; poses and masks checked against the simulator's ground truth."""

import json
import math

import numpy as np
import pytest

from n2d_capture.capture import CaptureConfig, capture
from n2d_capture.masks import iou
from n2d_capture.sweep import SweepConfig
from n2d_capture.turntable import Turntable, TurntableConfig
from n2d_common.contracts import open_stage
from n2d_common.errors import ContractError
from n2d_common.formats.session import read_session
from n2d_common.frames import inv_T, rot_z
from n2d_common.images import read_png
from n2d_sim.camera import SimCamera
from n2d_sim.frame_source import SimFrameSource
from n2d_sim.world import SimWorldConfig, T_cam_turntable

pytestmark = pytest.mark.slow  # real rendering, training or ROS round trips: tens of seconds or more


def _rotation_deg(R):
    return math.degrees(math.acos(np.clip((np.trace(R) - 1) / 2, -1, 1)))


@pytest.mark.timeout(600)
def test_capture_session_poses_and_masks_match_ground_truth(tmp_path, sim):
    world = SimWorldConfig(object="box")  # 640x480: the markers need ~3 px per bit
    cfg = CaptureConfig(sweep=SweepConfig(views=8))
    out = tmp_path / "session"
    truth = {}
    with SimCamera(world) as camera, Turntable(TurntableConfig(port=sim.link, velocity_limit_rad_s=4.0,
                                                                acceleration_rad_s2=20.0, settle_time_s=0.05)) as table:
        source = SimFrameSource(camera, lambda: sim.control.state()["plate_rad"])
        source.object_visible = False
        first = capture(out, cfg, table, source, empty_plate=True)
        assert not first["complete"] and not out.exists()
        with pytest.raises(ContractError, match="incomplete|does not exist"):
            open_stage(out, "capture_session")
        source.object_visible = True

        class Recording:  # remember the true plate angle of each view (ground truth)
            def grab(self, after_s, timeout_s):
                frame = source.grab(after_s, timeout_s)
                truth[frame.stamp_s] = (source.last.angle_rad, source.last.mask)
                return frame

        summary = capture(out, cfg, table, Recording())
    assert summary["complete"] and summary["views"] == 8

    session = read_session(out)
    assert len(session.views) == 8 and np.allclose(session.K, camera.K)
    T_cam_tt = T_cam_turntable(world)
    rot_err, trans_err, ious = [], [], []
    stamps = [v["stamp_s"] for v in json.loads((out / "capture.json").read_text())["views"]]
    for view, stamp in zip(session.views, stamps):
        angle, gt_mask = truth[stamp]
        gt = inv_T(T_cam_tt @ rot_z(angle))  # camera in the plate-attached turntable frame
        rot_err.append(_rotation_deg(view.T_turntable_cam[:3, :3].T @ gt[:3, :3]))
        trans_err.append(1000 * np.linalg.norm(view.T_turntable_cam[:3, 3] - gt[:3, 3]))
        ious.append(iou(read_png(view.mask) > 0, gt_mask))
    assert np.median(rot_err) < 0.15 and max(rot_err) < 0.5, rot_err
    assert np.median(trans_err) < 1.5 and max(trans_err) < 5.0, trans_err
    assert np.mean(ious) > 0.97, ious

    t = json.loads((out / "transforms.json").read_text())
    assert {"camera_model", "fl_x", "fl_y", "cx", "cy", "w", "h", "frames"} <= set(t)
    assert {"file_path", "mask_path", "transform_matrix"} <= set(t["frames"][0])
    info = json.loads((out / "capture.json").read_text())
    assert info["fit_on"] == "empty" and info["empty_views"] == 8
    assert read_png(out / "contact_sheet.png").ndim == 3
