"""``avoid-companion``: command-line front of the companion process (subcommands in their own modules)."""

from __future__ import annotations

import sys

from companion.cli import run_cli

# subcommand name -> (module providing configure_parser/command, one-line help)
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "run": ("companion.app", "run the companion: lidar -> policy -> safety shield -> autopilot setpoints"),
    "params": ("companion.params.check", "check or apply the autopilot parameters the companion relies on"),
    "replay": ("companion.replay", "run a flight recording through scan, stack, policy and shield again"),
}


def main(argv: list[str] | None = None) -> int:
    return run_cli(
        "avoid-companion",
        "Lidar obstacle avoidance on the companion computer: lidar -> policy -> autopilot.",
        SUBCOMMANDS,
        argv,
    )


if __name__ == "__main__":
    sys.exit(main())
