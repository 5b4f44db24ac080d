"""Test-wide setup: every test talks ROS only on localhost, in a ROS_DOMAIN_ID of its own."""

import itertools
import os

import pytest

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
os.environ.setdefault("HOME", "/tmp")

# Domain ids 1..100, offset by the process id so parallel test runs on one machine do not meet.
_domains = itertools.count()


@pytest.fixture
def ros_domain(monkeypatch) -> int:
    """A fresh ROS_DOMAIN_ID for this test, exported to the subprocesses it starts."""
    domain = 1 + (os.getpid() * 7 + next(_domains)) % 100
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain))
    from n2d_common.ros import ros_environment

    ros_environment(domain)
    return domain
