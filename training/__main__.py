"""``avoid-train``: command-line front of the training pipeline (subcommands in their own modules)."""

from __future__ import annotations

import sys

from companion.cli import run_cli

#: Top-level modules of the ``[train]`` extra (and the ``[sim]`` it includes): without them
#: ``avoid-train`` cannot run, and the user is told which extra to install instead of a traceback.
TRAIN_EXTRA_MODULES = frozenset(
    {"torch", "stable_baselines3", "gymnasium", "jsbsim", "numba", "matplotlib", "tensorboard", "tqdm",
     "rich", "onnx", "onnxscript"}
)  # fmt: skip

# subcommand name -> (module providing configure_parser/command, one-line help)
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "train": ("training.train", "train a PPO policy from a TOML config (checkpoints, evaluation, resume)"),
    "evaluate": ("training.evaluate", "fly a policy and the baselines over worlds; success table, JSON, PNG"),
    "export": ("training.export", "export a checkpoint's deterministic actor to ONNX and check parity"),
    "symmetrise": ("training.symmetrise", "make an exported policy answer a world and its mirror alike"),
    "trace": ("training.trace", "fly one episode of an evaluation and print every command, step by step"),
}


def main(argv: list[str] | None = None) -> int:
    try:
        return run_cli(
            "avoid-train",
            "Train, evaluate and export the obstacle-avoidance policy (PPO, stable-baselines3).",
            SUBCOMMANDS,
            argv,
        )
    except KeyboardInterrupt:  # outside learn (start-up, evaluation, export): nothing to save
        print("avoid-train: interrupted", file=sys.stderr)
        return 130
    except ModuleNotFoundError as exc:
        if (exc.name or "").split(".")[0] not in TRAIN_EXTRA_MODULES:
            raise
        print(
            f"avoid-train: error: {exc.name} is not installed; avoid-train needs the training extra: "
            "pip install -e '.[train]' (see docs/training.md)",
            file=sys.stderr,
        )
        return 2


if __name__ == "__main__":
    sys.exit(main())
