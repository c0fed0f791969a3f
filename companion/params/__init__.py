"""Autopilot parameters: the files that say what the autopilot should hold, the MAVLink parameter
client, the float encodings, and ``avoid-companion params check|apply``.

Imports the autopilot's connection helpers and common."""
