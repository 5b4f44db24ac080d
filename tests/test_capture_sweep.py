"""Capture sweeps through the real driver on the emulated servo (another process) and the rendered camera:
fresh frames at the commanded angles, and a sweep that dies half way resumes without retaking views."""

import math

import pytest

from n2d_capture.sweep import SweepConfig, read_sweep, run_sweep
from n2d_capture.turntable import ServoNotResponding, Turntable, TurntableConfig
from n2d_common.images import read_png
from n2d_sim.camera import SimCamera
from n2d_sim.frame_source import SimFrameSource
from n2d_sim.world import SimWorldConfig


class FailingRotator:
    """The real driver, with the servo told to stop answering before stop number `fail_at` (fault injection)."""

    def __init__(self, table, control, fail_at):
        self.table, self.control, self.fail_at, self.calls = table, control, fail_at, []

    def rotate_to(self, angle):
        if len(self.calls) == self.fail_at:
            self.control.fault("no_reply")
        self.calls.append(angle)
        return self.table.rotate_to(angle)


@pytest.fixture(scope="module")
def camera():
    with SimCamera(SimWorldConfig(width=160, height=120, focal_px=150.0, samples=2, background_samples=4)) as cam:
        yield cam


@pytest.mark.timeout(300)
def test_sweep_takes_fresh_views_and_resumes_after_a_servo_fault(tmp_path, sim, camera):
    cfg = SweepConfig(views=4)
    source = SimFrameSource(camera, lambda: sim.control.state()["plate_rad"])
    table_cfg = TurntableConfig(port=sim.link, velocity_limit_rad_s=4.0, acceleration_rad_s2=20.0,
                                settle_time_s=0.05, retries=1)
    with Turntable(table_cfg) as table:
        failing = FailingRotator(table, sim.control, fail_at=2)
        with pytest.raises(ServoNotResponding):
            run_sweep(tmp_path, "images", cfg, failing, source)
    views = read_sweep(tmp_path, "images")
    assert [v["index"] for v in views] == [0, 1]  # what was taken is kept
    kept = (tmp_path / "images/0001.png").stat().st_mtime_ns

    sim.control.fault("none")
    with Turntable(table_cfg) as table:
        resumed = FailingRotator(table, sim.control, fail_at=-1)
        views = run_sweep(tmp_path, "images", cfg, resumed, source)
    assert [round(a, 6) for a in resumed.calls] == [round(math.pi, 6), round(1.5 * math.pi, 6)]
    assert (tmp_path / "images/0001.png").stat().st_mtime_ns == kept
    assert [v["file"] for v in views] == [f"images/{i:04d}.png" for i in range(4)]
    for v in views:
        assert abs(v["angle_rad"] - v["angle_cmd_rad"]) < 0.005
        assert v["stamp_s"] >= v["settled_s"]  # never a frame from before the plate settled
        assert read_png(tmp_path / v["file"]).shape == (120, 160, 3)
    assert abs(source.last.angle_rad - views[-1]["angle_rad"]) < 0.005
