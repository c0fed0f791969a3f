"""``avoid-sim demo``: which worlds it flies and how it rejects bad command lines."""

from __future__ import annotations

from pathlib import Path

import pytest

from flightsim.__main__ import main
from flightsim.demo import GENERATED, demo_worlds
from flightsim.harness import default_policy


def test_demo_flies_the_generated_rooms_then_every_shipped_example_world() -> None:
    names = [w.name for w in demo_worlds()]
    shipped = sorted(p.stem for p in (Path(__file__).parents[2] / "flightsim" / "worlds").glob("*.json"))
    assert len(names) == len(GENERATED) + len(shipped)
    assert shipped and set(shipped) <= set(names)


def test_the_shipped_policy_is_the_demo_default() -> None:
    assert default_policy().is_file()


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["demo", "--duration", "0"], "--duration must be positive, got 0.0"),
        (["demo", "--policy", "no/such/policy.onnx"], "policy file not found: no/such/policy.onnx"),
    ],
)
def test_bad_demo_command_line_is_one_line_and_exit_2(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    assert main([*argv, "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"avoid-sim: error: {message}"
