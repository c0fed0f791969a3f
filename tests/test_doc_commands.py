"""Every command the README and the docs mark runnable works as written, with the shipped model.

A shell block preceded by ``<!-- run -->`` is run here line by line (a Python block whole), in
a scratch directory that sees the repository's files (``models/policy.onnx``,
``training/configs/``, ``flightsim/worlds/``) where the docs say they are; a line that an earlier
block already ran is run once. Where the full run takes minutes, the command runs in a cheap
form: the substitutions below change only how long it runs (fewer worlds, seconds, steps), never
what it is, and each says why. A block that cannot run here says why in its
``<!-- norun: ... -->`` marker (tests/test_docs.py checks that every block has one of the two).
"""

from __future__ import annotations

import os
import re
import subprocess
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = ["README.md", *sorted(str(p.relative_to(REPO)) for p in (REPO / "docs").glob("*.md"))]
#: what the scratch directory links to, so that repository paths in the commands resolve
LINKED = ("companion", "flightsim", "training", "models", "config", "firmware_params", "systemd", "docs")

#: (the command starts with, text, replaced by, why): the cheap form of a long command
CHEAP: list[tuple[str, str, str, str]] = [
    ("python3 -m venv", "python3 -m venv .venv && . .venv/bin/activate && pip install -e '.[sim]' && ", "",
     "the tests run where the project is installed; CI installs it from scratch"),
    ("avoid-sim demo", "avoid-sim demo", "avoid-sim demo --duration 4",
     "every flight starts, engages and reports, then flies 4 s instead of its whole mission"),
    ("avoid-sim fly", "\n", " --duration 6\n",
     "the flight starts, engages and reports (and records), then flies 6 s (a later --duration wins)"),
    ("avoid-train evaluate", "--seeds 20", "--seeds 1", "1 test world per family instead of 20"),
    ("avoid-train train", "pretrain.iterations=4",
     "pretrain.iterations=1 pretrain.steps=128 pretrain.epochs=1 eval.n_worlds=1 n_envs=1 "
     "'env.families=[\"rooms\"]'",
     "one DAgger iteration of 128 steps instead of four of 60,000, evaluated on one world"),
    ("avoid-train export", "dagger_240000_steps", "dagger_128_steps", "the cheap training's only checkpoint"),
    ("avoid-train export", "dagger_180000_steps", "dagger_128_steps", "the cheap training's only checkpoint"),
    ("avoid-train export", "--out", "--parity-samples 50 --out", "parity on 50 observations, not 1,000"),
]  # fmt: skip

_already_ran: set[str] = set()


def runnable_blocks() -> list[tuple[str, list[str]]]:
    """(``doc:line``, its commands) of every block marked ``<!-- run -->``, continuation lines joined."""
    blocks = []
    for doc in DOCS:
        text = (REPO / doc).read_text()
        for match in re.finditer(r"<!-- run -->\n```(sh|bash|python)\n(.*?)```", text, re.S):
            line_no = text[: match.start()].count("\n") + 2
            if match.group(1) == "python":
                blocks.append((f"{doc}:{line_no}", [f"python3 - <<'EOF'\n{match.group(2)}EOF"]))
                continue
            body = match.group(2).replace("\\\n", " ")
            commands = [line.strip() for line in body.splitlines() if line.strip() and line[0] != "#"]
            blocks.append((f"{doc}:{line_no}", commands))
    return blocks


def cheap(command: str) -> str:
    """``command`` in its cheap form (:data:`CHEAP`)."""
    command += "\n"
    for prefix, old, new, _why in CHEAP:
        if command.startswith(prefix):
            command = command.replace(old, new)
    return command.strip()


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    """A scratch directory where the repository's paths resolve and the commands' output goes."""
    path = tmp_path_factory.mktemp("doc-commands")
    for name in LINKED:
        (path / name).symlink_to(REPO / name)
    return path


def test_every_runnable_command_names_a_program_of_the_project():
    blocks = runnable_blocks()
    assert len(blocks) >= 10, "the docs mark fewer runnable blocks than they did"
    for where, commands in blocks:
        for command in commands:
            program = r"(avoid-(sim|train|companion)|python3 -m venv|python3 -) "
            assert re.match(program, command), (where, command)


def test_the_cheap_forms_change_only_how_long_a_command_runs():
    assert cheap("avoid-train evaluate --seeds 20 --shield") == "avoid-train evaluate --seeds 1 --shield"
    assert cheap("avoid-sim fly --world w.json --duration 20") == (
        "avoid-sim fly --world w.json --duration 20 --duration 6"
    )
    assert cheap("avoid-sim worlds --gallery g.png") == "avoid-sim worlds --gallery g.png"


@pytest.mark.timeout(900)
@pytest.mark.parametrize(("where", "commands"), runnable_blocks(), ids=[b[0] for b in runnable_blocks()])
def test_the_documented_commands_run_with_the_shipped_model(where, commands, workdir):
    path = os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))
    env = {**os.environ, "PYTHONPATH": path}
    for command in commands:
        run = cheap(command)
        if run in _already_ran:
            continue
        start = time.monotonic()
        result = subprocess.run(["bash", "-c", run], cwd=workdir, env=env, capture_output=True, text=True,
                                timeout=600)  # fmt: skip
        took = time.monotonic() - start
        assert result.returncode == 0, (
            f"{where}: `{command}` (run as `{run}`) exited {result.returncode} after {took:.0f} s:\n"
            f"{result.stderr[-3000:]}"
        )
        print(f"{where}: {took:6.1f} s  {run}")
        _already_ran.add(run)
