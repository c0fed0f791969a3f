"""Software in the loop: the real companion process flying a simulated or external autopilot over
MAVLink, the simulated autopilots, the demo, flight recording and reports.

The top of flightsim: imports envs, vehicle and worlds."""
