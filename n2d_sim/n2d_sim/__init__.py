"""The embedded simulated world of n2d: a Dynamixel X-series servo emulated on a pseudo-terminal, a
Cycles-rendered turntable camera with ground truth, and the shipped sample objects.
"""
