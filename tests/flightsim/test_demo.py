"""``avoid-sim demo``: which worlds it flies, for how long, how it rejects bad command lines, and
that Ctrl-C ends every flight it has in the air (the real command, SIGINT to its process group)."""

from __future__ import annotations

import json
from concurrent.futures import Future
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path

import pytest

from companion.common.errors import UserError
from flightsim.__main__ import main
from flightsim.envs import seeds
from flightsim.envs.env import CONTROL_HZ
from flightsim.envs.nav_env import LidarNavEnv
from flightsim.sitl.demo import (
    GENERATED,
    LANES,
    _progress,
    _result,
    _table,
    demo_worlds,
    lane_schedule,
    time_limit,
    validation_worlds,
)
from flightsim.sitl.flight_report import FlightReport
from flightsim.sitl.fly_cli import default_policy
from flightsim.sitl.harness import FlightOptions
from flightsim.worlds.families import FAMILIES
from tests.foreground import ctrl_c_once_flying, running_in_group, start_foreground


def test_demo_flies_missions_in_generated_worlds_of_different_families_then_every_example_world() -> None:
    worlds = demo_worlds()
    names = [w.name for w in worlds]
    shipped = sorted(p.stem for p in (Path(__file__).parents[2] / "flightsim" / "worlds").glob("*.json"))
    assert len(names) == len(GENERATED) + len(shipped)
    assert shipped and set(shipped) <= set(names)
    families = [family for family, _, _ in GENERATED]
    assert len(set(families)) == len(families) >= 3
    assert all(w.waypoints for w in worlds)  # every flight is a mission


def test_the_validation_sweep_flies_every_family_twice_on_validation_seeds_only() -> None:
    """``--worlds validation``: each family at two difficulties, each world its own seed, every seed a
    validation one (never a test seed, as the demo's generated worlds are)."""
    worlds = validation_worlds()
    names = [w.name for w in worlds]
    assert len(set(names)) == len(names) == 2 * len(FAMILIES)
    assert sorted(n.split("-")[0] for n in names) == sorted(list(FAMILIES) * 2)
    used = {int(n.split("-")[1]) for n in names}
    assert used <= set(seeds.VALIDATION) and not used & {seed for _, seed, _ in GENERATED}
    assert {n.rsplit("-d", 1)[1] for n in names} == {"0.35", "0.75"}
    assert all(w.waypoints for w in worlds)


def test_a_demo_mission_gets_the_time_an_evaluation_episode_of_its_world_gets() -> None:
    """The demo judges a mission as ``avoid-train evaluate`` judges an episode: the same time limit
    (the environment's, from the world's shortest safe path)."""
    env = LidarNavEnv()
    for world in demo_worlds():
        env.reset(seed=0, options={"world": world})
        assert time_limit(world) == pytest.approx(env.time_limit_steps / CONTROL_HZ), world.name


def test_lanes_take_the_flights_in_order_each_on_the_first_lane_free() -> None:
    assert lane_schedule([50.0, 40.0, 30.0, 20.0], lanes=2) == 70.0  # 50 | 40+30, then 50+20
    assert lane_schedule([10.0, 10.0, 10.0], lanes=1) == 30.0
    assert lane_schedule([], lanes=2) == 0.0


def test_demo_time_limits_leave_room_for_start_up_within_three_minutes() -> None:
    """Every flight timed out, the demo still ends within 3 min: 9 s each for start-up, take-off,
    engaging and the report (measured with every flight timed out, load average 17 on 2 cores)
    beside the flights' time limits, the flights :data:`LANES` at a time."""
    worlds = demo_worlds()
    assert lane_schedule([time_limit(w) + 9.0 for w in worlds], LANES) <= 170.0


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


def _report(world: str, reached: int = 2) -> FlightReport:
    report = FlightReport(world, "sim-ardupilot", True, False, 30.0, 41.5, 0.8, 10.0, 4.0, 7.0, [], {})
    report.waypoints_total, report.mission_complete, report.mission_time_s = 2, reached == 2, 28.4
    report.waypoints_reached = [(i, 10.0 * (i + 1)) for i in range(reached)]
    return report


def test_the_table_fits_long_world_names_and_each_flight_has_one_row() -> None:
    reports = [_report("pillars-900001-d0.30"), _report("a-much-longer-world-name-than-twenty", 1)]
    lines = _table(reports).splitlines()
    header = next(line for line in lines if line.startswith("world"))
    rows = [line for line in lines if line.startswith(("pillars", "a-much"))]
    assert len(rows) == 2
    # every row's columns end where the header's do, however long the world's name
    assert {len(row) for row in rows} == {len(header)}
    assert [row.split()[1:] for row in rows] == [
        ["yes", "2/2", "yes", "28.4", "no", "41.5", "0.80"],
        ["yes", "1/2", "no", "n/a", "no", "41.5", "0.80"],
    ]


def test_flights_without_missions_are_counted_as_flights() -> None:
    """A scan-only model flies no missions: the last line counts flights without a collision."""
    mission = _table([_report("a"), _report("b", 1)])
    assert "1/2 missions complete without collision" in mission
    flown = _report("a")
    flown.waypoints_total, flown.waypoints_reached, flown.mission_complete = 0, [], False
    crashed = _report("b")
    crashed.waypoints_total, crashed.collision = 0, True
    assert "1/2 flights without collision" in _table([flown, crashed])


def test_a_flight_ending_prints_a_labelled_line_not_a_table_row() -> None:
    report = _report("pillars-900001-d0.30")
    assert _progress(3, 6, report) == "[3/6] pillars-900001-d0.30: 2/2 waypoints, complete in 28.4 s"
    assert _progress(1, 6, _report("x", 1)) == "[1/6] x: 1/2 waypoints, not complete"
    failed = FlightReport.failed("x", "sim-px4", "interrupted")
    assert _progress(2, 6, failed) == "[2/6] x: error: interrupted"


def test_an_unknown_world_set_is_named_in_the_error_and_exit_2(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exited:
        main(["demo", "--worlds", "nope"])
    assert exited.value.code == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith("avoid-sim demo: error: argument --worlds: invalid choice: 'nope'")


def test_a_flight_cancelled_is_interrupted_one_whose_process_died_says_so_any_other_error_is_raised() -> None:
    options = FlightOptions(autopilot="sim-ardupilot", world=demo_worlds()[-1], policy=default_policy())
    cancelled: Future[FlightReport] = Future()
    cancelled.cancel()
    assert _result(cancelled, options).error == "interrupted"
    died: Future[FlightReport] = Future()
    died.set_exception(BrokenProcessPool("a process terminated abruptly"))
    assert _result(died, options).error.startswith("its process died")
    failed: Future[FlightReport] = Future()
    failed.set_exception(UserError("policy file not found: x.onnx"))
    with pytest.raises(UserError, match="policy file not found"):
        _result(failed, options)


def test_ctrl_c_ends_the_flights_in_the_air_and_cancels_the_rest(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    proc = start_foreground("flightsim", "demo", "--out", str(out))
    stdout, stderr = ctrl_c_once_flying(proc, out, flights=LANES)  # a flight in every lane
    assert proc.returncode == 130, stdout + stderr
    assert "Traceback" not in stdout + stderr
    flights = json.loads((out / "summary.json").read_text())["flights"]
    assert [f["world"] for f in flights] == [w.name for w in demo_worlds()]
    assert all(f["error"] == "interrupted" for f in flights), [f["error"] for f in flights]
    assert sum(f["engaged"] for f in flights) <= LANES  # no flight started after the Ctrl-C
    assert running_in_group(proc.pid) == []  # nothing of the demo is left running

