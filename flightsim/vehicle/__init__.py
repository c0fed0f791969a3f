"""The simulated vehicle: the JSBSim quadrotor, its cascaded controller and the firmware response
models it flies through.

Imports nothing else of flightsim."""
