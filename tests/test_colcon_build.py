"""`colcon build` of the repo (the path for labs with a system ROS 2 install) finds and builds every package."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # real rendering, training or ROS round trips: tens of seconds or more

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.timeout(600)
def test_colcon_builds_all_packages(tmp_path):
    files = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    for rel in filter(None, files.decode().split("\0")):
        src, dst = ROOT / rel, tmp_path / rel
        dst.parent.mkdir(parents=True, exist_ok=True)
        if src.is_symlink():
            dst.symlink_to(os.readlink(src))
        elif src.is_file():
            dst.write_bytes(src.read_bytes())
    venv = Path(sys.prefix)
    env = {**os.environ, "AMENT_PREFIX_PATH": str(venv), "CMAKE_PREFIX_PATH": str(venv)}
    listed = subprocess.run([str(venv / "bin" / "colcon"), "list", "--names-only"], cwd=tmp_path, env=env,
                            capture_output=True, text=True, check=True).stdout.split()
    assert sorted(listed) == ["n2d", "n2d_blender", "n2d_capture", "n2d_common", "n2d_dataset", "n2d_dope",
                              "n2d_interfaces", "n2d_reconstruct", "n2d_sim"]
    build = subprocess.run([str(venv / "bin" / "colcon"), "build", "--cmake-args", "-G", "Ninja",
                            "-DBUILD_TESTING=OFF", f"-DPython3_EXECUTABLE={sys.executable}"],
                           cwd=tmp_path, env=env, capture_output=True, text=True)
    assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]
    install = tmp_path / "install"
    assert (install / "n2d/share/n2d/launch/sim.launch.py").is_file()
    assert (install / "n2d/share/n2d/launch/sim.yaml").is_file()
    assert (install / "n2d_sim/lib/n2d_sim/sim_camera_node").is_file()
    assert (install / "n2d_sim/lib/n2d_sim/sim_turntable_node").is_file()
    assert (install / "n2d_interfaces/share/n2d_interfaces/action/Capture.action").is_file()
    assert (install / "n2d/share/ament_index/resource_index/packages/n2d").is_file()
