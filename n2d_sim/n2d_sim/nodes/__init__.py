"""ROS 2 nodes of the simulated world (one node per module, thin shells over the sim library)."""
