"""ROS 2 launch file of the whole pipeline; the node list lives in pipeline.yaml (shared with
`n2d launch pipeline` and `n2d demo`)."""

from pathlib import Path

from n2d.launch_description import ros_launch_description


def generate_launch_description():
    return ros_launch_description(Path(__file__).with_name("pipeline.yaml"))
