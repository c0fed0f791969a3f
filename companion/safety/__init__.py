"""What the vehicle may do, whatever the policy asks: the safety shield and the supervisor that
holds on stale inputs.

Imports perception, the autopilot's link types and common; never guidance or the app."""
