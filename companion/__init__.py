"""lidar-avoid companion: the process that flies the learned policy on the drone.

Runtime dependencies only (numpy, onnxruntime, pymavlink, python-can, velodyne-decoder);
never torch, jsbsim or gymnasium.
"""
