"""ROS 2 launch file of live DOPE pose estimation; the node list lives in dope.yaml (shared with
`n2d launch dope`)."""

from pathlib import Path

from n2d.launch_description import ros_launch_description


def generate_launch_description():
    return ros_launch_description(Path(__file__).with_name("dope.yaml"))
