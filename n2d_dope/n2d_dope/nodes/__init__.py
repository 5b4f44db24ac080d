"""ROS 2 nodes of the DOPE stage (one node per module, thin shells over n2d_dope)."""
