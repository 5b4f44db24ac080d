"""ROS 2 nodes of the capture stage (one node per module, thin shells over n2d_capture)."""
