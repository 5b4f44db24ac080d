"""ROS 2 launch file of the DOPE training stage; the node list lives in train.yaml (shared with
`n2d launch train`)."""

from pathlib import Path

from n2d.launch_description import ros_launch_description


def generate_launch_description():
    return ros_launch_description(Path(__file__).with_name("train.yaml"))
