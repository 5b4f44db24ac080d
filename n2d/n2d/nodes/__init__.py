"""ROS 2 nodes of the n2d bringup package."""
