"""Shared core of n2d: on-disk contracts (n2d.json manifests, atomic stage directories), typed configs,
frames, progress, and the few ROS 2 helpers the nodes share.
"""

__version__ = "0.1.0"
