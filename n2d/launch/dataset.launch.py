"""ROS 2 launch file of the dataset stage; the node list lives in dataset.yaml (shared with
`n2d launch dataset`)."""

from pathlib import Path

from n2d.launch_description import ros_launch_description


def generate_launch_description():
    return ros_launch_description(Path(__file__).with_name("dataset.yaml"))
