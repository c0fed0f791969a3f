"""The autopilot links: MAVLink to ArduPilot (GUIDED) and PX4 (OFFBOARD through MAVSDK), message
signing, connection strings, and the OBSTACLE_DISTANCE message built from the scan.

Imports perception and common.
"""
