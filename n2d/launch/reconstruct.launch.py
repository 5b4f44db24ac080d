"""ROS 2 launch file of the reconstruction stage; the node list lives in reconstruct.yaml (shared with
`n2d launch reconstruct`)."""

from pathlib import Path

from n2d.launch_description import ros_launch_description


def generate_launch_description():
    return ros_launch_description(Path(__file__).with_name("reconstruct.yaml"))
