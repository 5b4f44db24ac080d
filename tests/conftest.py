"""Test-wide setup: every test talks ROS only on localhost, in a ROS_DOMAIN_ID of its own; shared fixtures."""

import itertools
import os
import secrets
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import pytest

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("HOME", "/tmp")
# Every Ray of the tests (in this process and the nodes they start) takes one token of this run, whatever ~/.ray
# holds, and sends no telemetry; set before any import of Ray, which reads its auth settings once per process.
os.environ.update({"RAY_USAGE_STATS_ENABLED": "0", "RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": secrets.token_hex(32)})

# Domain ids 1..88, offset by the process id so parallel test runs on one machine do not meet; the benchmarks
# that start nodes use 89..100 (below 102: higher ids reach into Linux's ephemeral port range).
_domains = itertools.count()


@pytest.fixture
def ros_domain(monkeypatch) -> int:
    """A fresh ROS_DOMAIN_ID for this test, exported to the subprocesses it starts."""
    domain = 1 + (os.getpid() * 7 + next(_domains)) % 88
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain))
    from n2d_common.ros import ros_environment

    ros_environment(domain)
    return domain


@dataclass
class ServoSim:
    """A standalone servo emulator process: its port (symlink), control client and process."""

    link: str
    control: object
    proc: subprocess.Popen


@pytest.fixture
def sim():
    """A standalone emulator process (id 1) behind a symlink, with its control socket."""
    from n2d_common.errors import DeviceError
    from n2d_sim.servo import ServoControl

    with tempfile.TemporaryDirectory(prefix="n2d-servo-") as tmp:  # short path: AF_UNIX names are limited
        link, control, log = Path(tmp) / "ttyDXL", Path(tmp) / "ctl", Path(tmp) / "log"
        with open(log, "w") as out:
            proc = subprocess.Popen([sys.executable, "-m", "n2d_sim.servo", "--link", str(link),
                                     "--control", str(control)], stdout=out, stderr=subprocess.STDOUT)
        ctl = ServoControl(control)
        try:
            ctl.wait_ready(timeout_s=15)
        except DeviceError:
            proc.kill()
            pytest.fail(f"emulator did not start:\n{log.read_text()}")
        yield ServoSim(str(link), ctl, proc)
        if proc.poll() is None:
            proc.terminate()
            assert proc.wait(timeout=5) == 0, log.read_text()
        assert not link.is_symlink(), "the emulator left its symlink behind"
