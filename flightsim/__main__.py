"""``avoid-sim``: command-line front of the flight simulator (subcommands in their own modules)."""

from __future__ import annotations

import sys

from companion.cli import run_cli

# subcommand name -> (module providing configure_parser/command, one-line help)
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "fly": (
        "flightsim.sitl.fly_cli", "SITL flight: the real companion flying a simulated or external autopilot"
    ),
    "autopilot": ("flightsim.sitl.sim_autopilot.server", "a simulated ArduCopter/PX4 on MAVLink sockets"),
    "demo": (
        "flightsim.sitl.demo", "a few short SITL flights in generated and example rooms (under 3 minutes)"
    ),
    "worlds": (
        "flightsim.worlds.gallery", "the world families: a PNG gallery (--gallery) and world files (--save)"
    ),
    "report": ("flightsim.sitl.recording_report", "picture of a flight from its MCAP recording: path, speed, "
               "clearance, shield, states"),
}


def main(argv: list[str] | None = None) -> int:
    return run_cli(
        "avoid-sim",
        "Simulator: JSBSim quadrotor, lidar, worlds, simulated autopilot and SITL flights.",
        SUBCOMMANDS,
        argv,
    )


if __name__ == "__main__":
    sys.exit(main())
