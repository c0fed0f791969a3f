"""``avoid-sim demo``: which worlds it flies and how it rejects bad command lines."""

from __future__ import annotations

from pathlib import Path

import pytest

from flightsim.__main__ import main
from flightsim.demo import GENERATED, demo_worlds, time_limit
from flightsim.fly_cli import default_policy


def test_demo_flies_missions_in_generated_worlds_of_different_families_then_every_example_world() -> None:
    worlds = demo_worlds()
    names = [w.name for w in worlds]
    shipped = sorted(p.stem for p in (Path(__file__).parents[2] / "flightsim" / "worlds").glob("*.json"))
    assert len(names) == len(GENERATED) + len(shipped)
    assert shipped and set(shipped) <= set(names)
    families = [family for family, _, _ in GENERATED]
    assert len(set(families)) == len(families) >= 3
    assert all(w.waypoints for w in worlds)  # every flight is a mission


def test_demo_time_limits_leave_room_for_start_up_within_three_minutes() -> None:
    """Every flight timed out, the demo still ends within 3 min: 9 s each for start-up, take-off,
    engaging and the report (measured with every flight timed out, load average 17 on 2 cores)
    beside the flights' time limits."""
    worlds = demo_worlds()
    assert sum(time_limit(w) for w in worlds) + 9.0 * len(worlds) <= 170.0


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
