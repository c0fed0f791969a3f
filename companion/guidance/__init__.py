"""Where to fly: goals, mission items, the route planner, and the ONNX policy that turns observations
into a velocity command.

Imports perception, the autopilot's message types and common; never safety or the app."""
