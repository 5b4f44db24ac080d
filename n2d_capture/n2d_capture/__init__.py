"""Capture stage of n2d: Dynamixel turntable driver, ChArUco board, capture sweeps that write metric,
posed, masked sessions.
"""
