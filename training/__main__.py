"""``avoid-train``: command-line front of the training pipeline (subcommands in their own modules)."""

from __future__ import annotations

import sys

from companion.cli import run_cli

# subcommand name -> (module providing configure_parser/command, one-line help)
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "train": ("training.train", "train a PPO policy from a TOML config (checkpoints, evaluation, resume)"),
    "evaluate": ("training.evaluate", "fly a policy and the baselines over worlds; success table, JSON, PNG"),
    "export": ("training.export", "export a checkpoint's deterministic actor to ONNX and check parity"),
}


def main(argv: list[str] | None = None) -> int:
    return run_cli(
        "avoid-train",
        "Train, evaluate and export the obstacle-avoidance policy (PPO, stable-baselines3).",
        SUBCOMMANDS,
        argv,
    )


if __name__ == "__main__":
    sys.exit(main())
