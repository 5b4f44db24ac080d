"""`n2d demo` end to end, as a user runs it: a subprocess, the simulated world, the real driver, files on disk."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from n2d_common.contracts import open_stage
from n2d_common.images import read_png

SMALL = ["--set", "views=3", "--set", "width=160", "--set", "height=120", "--set", "focal_px=150"]


@pytest.mark.timeout(600)
def test_demo_writes_a_complete_run_and_rerun_is_a_no_op(tmp_path, ros_domain):
    n2d = shutil.which("n2d", path=str(Path(sys.executable).parent))
    out = tmp_path / "run"
    cmd = [n2d, "demo", str(out), *SMALL, "--set", f"domain_id={ros_domain}"]
    first = subprocess.run(cmd, capture_output=True, text=True, timeout=540)
    assert first.returncode == 0, first.stderr[-2000:]
    assert "3 views" in first.stdout
    manifest = open_stage(out, "run")
    assert manifest["config"]["views"] == 3
    frames = json.loads((out / "frames.json").read_text())["frames"]
    assert [round(f["target_rad"], 4) for f in frames] == [0.0, 2.0944, 4.1888]
    for f in frames:
        assert abs(f["driver_rad"] - f["target_rad"]) < 0.005
        assert read_png(out / f["file"]).shape == (120, 160, 3)
    assert manifest["extra"]["max_driver_vs_truth_deg"] < 0.2
    assert read_png(out / "contact_sheet.png").ndim == 3
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert again.returncode == 0 and "complete already" in again.stdout
