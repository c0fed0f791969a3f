"""``avoid-train``: command-line front of the training pipeline (subcommands in their own modules)."""

from __future__ import annotations

import sys

from companion.cli import run_cli

# subcommand name -> (module providing configure_parser/command, one-line help)
SUBCOMMANDS: dict[str, tuple[str, str]] = {}


def main(argv: list[str] | None = None) -> int:
    return run_cli(
        "avoid-train",
        "Train, evaluate and export the obstacle-avoidance policy (PPO, stable-baselines3).",
        SUBCOMMANDS,
        argv,
    )


if __name__ == "__main__":
    sys.exit(main())
