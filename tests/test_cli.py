"""The n2d command: help, launch descriptions, and one clear error line (plus hint) for bad input."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from n2d.cli import main
from n2d.launch_description import load, resolve_arguments
from n2d.launcher import node_command
from n2d_common.errors import ConfigError


def _error_lines(capsys):
    err = capsys.readouterr().err.strip().splitlines()
    assert err[0].startswith("n2d: error: ")
    assert len(err) <= 2 and (len(err) == 1 or err[1].startswith("  hint: "))
    return err


def test_entry_point_help_lists_subcommands():
    n2d = shutil.which("n2d", path=str(Path(sys.executable).parent))
    out = subprocess.run([n2d, "--help"], capture_output=True, text=True, check=True).stdout
    for command in ("demo", "sim", "launch"):
        assert command in out
    out = subprocess.run([n2d, "demo", "--help"], capture_output=True, text=True, check=True).stdout
    assert "--overwrite" in out and "--set" in out


def test_launch_lists_descriptions(capsys):
    assert main(["launch"]) == 0
    out = capsys.readouterr().out
    assert "sim:" in out and "object:=box" in out


def test_unknown_launch_and_bad_argument(capsys):
    assert main(["launch", "nosuch"]) == 2
    assert "available: " in _error_lines(capsys)[1]
    assert main(["launch", "sim", "objekt:=mug"]) == 2
    assert "unknown argument" in _error_lines(capsys)[0]
    assert main(["launch", "sim", "object=mug"]) == 2
    assert "name:=value" in _error_lines(capsys)[0]


def test_bad_demo_config(tmp_path, capsys):
    assert main(["demo", str(tmp_path / "run"), "--set", "pipeline.views=0"]) == 2
    assert "views must be >= 1" in _error_lines(capsys)[0]
    assert main(["demo", str(tmp_path / "run"), "--set", "name=my mug"]) == 2
    assert "object name 'my mug' is not usable" in _error_lines(capsys)[0]
    bad = tmp_path / "bad.yaml"
    bad.write_text("live_views: [1,\n")
    assert main(["demo", str(tmp_path / "run"), "--config", str(bad)]) == 2
    assert "not valid YAML" in _error_lines(capsys)[0]
    assert not (tmp_path / "run").exists()


def test_demo_refuses_foreign_output_and_keeps_it(tmp_path, capsys):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("keep me")
    assert main(["demo", str(out)]) == 2
    assert "not an n2d run directory" in _error_lines(capsys)[0]
    assert (out / "notes.txt").read_text() == "keep me"


def test_sim_description_resolves_to_node_commands():
    spec = load("sim")
    args = resolve_arguments(spec, {"object": "bottle", "width": "320"})
    cmds = {n.name: node_command(n, args) for n in spec.nodes}
    cam = cmds["sim_camera"]
    assert cam[1:3] == ["-m", "n2d_sim.nodes.sim_camera_node"]
    assert "world.object:='bottle'" in cam and "world.width:=320" in cam and "rate_hz:=10.0" in cam
    assert "__ns:=/n2d" in cam
    with pytest.raises(ConfigError):
        resolve_arguments(spec, {"nope": "1"})


def test_launch_files_are_real_ros2_launch_files():
    # launch_ros is not installable here; check that each *.launch.py pairs with a YAML description
    # and builds through ros_launch_description (exercised on machines with ROS installed).
    launch = Path(__file__).resolve().parent.parent / "launch"
    files = sorted(launch.glob("*.launch.py"))
    assert files
    for f in files:
        text = f.read_text()
        assert "def generate_launch_description" in text and "ros_launch_description" in text
        assert f.with_name(f.name.replace(".launch.py", ".yaml")).is_file()
        load(f.name.replace(".launch.py", ""))


def test_capture_import_of_a_missing_folder(tmp_path, capsys):
    assert main(["capture", "import", str(tmp_path / "nope"), str(tmp_path / "session")]) == 2
    assert "does not exist" in _error_lines(capsys)[0]
    assert not (tmp_path / "session").exists() and not (tmp_path / "session.partial").exists()


def test_capture_reads_the_board_json_that_n2d_board_writes(tmp_path, capsys):
    import argparse

    from n2d.cli import _capture_config

    assert main(["board", str(tmp_path / "board"), "--set", "squares_x=5", "--set", "square_m=0.035"]) == 0
    args = argparse.Namespace(config=None, set=["pose_from=colmap"], board=tmp_path / "board" / "board.json")
    cfg = _capture_config(args)
    assert (cfg.board.squares_x, cfg.board.square_m, cfg.pose_from) == (5, 0.035, "colmap")

    (tmp_path / "bad.json").write_text('{"squares_x": 5, "square_mm": 35}')
    capsys.readouterr()
    assert main(["capture", "import", str(tmp_path / "photos"), str(tmp_path / "session"),
                 "--board", str(tmp_path / "bad.json")]) == 2
    assert "square_mm" in _error_lines(capsys)[0]
