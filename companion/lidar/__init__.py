"""The lidar drivers: Velodyne VLP-16 UDP packets and CAN rangefinder rings, each to returns.

Imports common and the config types only.
"""
