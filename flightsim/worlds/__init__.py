"""Worlds: the schema and loader, the generated families, the path planner and the top-down render.
The example world files (``*.json``) live here too.

Imports nothing else of flightsim."""
