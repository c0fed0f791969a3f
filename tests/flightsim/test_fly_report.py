"""``avoid-sim fly``'s report never shows a -1 sentinel, and Ctrl-C during a flight exits 130.

The Ctrl-C test runs the real command (simulated ArduPilot, the companion as its own process) and
sends SIGINT to the whole process group, as a terminal does.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from flightsim.sitl.demo import _row
from flightsim.sitl.flight_report import FlightReport, print_report
from tests.foreground import ctrl_c_once_flying, start_foreground

REPO = Path(__file__).resolve().parents[2]


def test_a_flight_that_measured_nothing_says_n_a(capsys):
    report = FlightReport.failed("two-pillars", "sim-px4", "the companion exited (status 2): ...")
    print_report(report)
    out = capsys.readouterr().out
    assert "minimum clearance n/a" in out and "p50 n/a, p99 n/a" in out
    assert "-1" not in out
    data = json.loads(report.to_json())
    assert data["min_clearance_m"] is None and data["latency_p50_ms"] is None
    assert "n/a" in _row(report) and "-1" not in _row(report)


def test_ctrl_c_during_a_flight_exits_130(tmp_path):
    fly = ("fly", "--seed", "3", "--duration", "60", "--lidar-step", "1.0", "--workdir", str(tmp_path))
    proc = start_foreground("flightsim", *fly)
    out, err = ctrl_c_once_flying(proc, tmp_path)
    assert proc.returncode == 130, out + err
    assert "Traceback" not in out + err
    assert "error: interrupted" in out


def test_the_flight_png_has_a_legend(tmp_path):
    from flightsim.sitl.flight_report import plot_flight
    from flightsim.worlds.world import load_world

    world = load_world(REPO / "flightsim" / "worlds" / "two-pillars.json")
    t = np.linspace(0.0, 10.0, 50)
    traj = np.column_stack(
        [t, -4.5 + 0.3 * t, 0.1 * t, np.full_like(t, 1.5), np.zeros_like(t), np.ones_like(t)]
    )
    fig = plot_flight(world, traj, engaged_at=4.0, collision_at=None, path=tmp_path / "f.png", title="t")
    names = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert "take-off and hold (ground station)" in names and "companion flying" in names
    assert (tmp_path / "f.png").read_bytes()[:4] == b"\x89PNG"


def test_the_flight_png_legend_is_beside_the_map_within_the_picture(tmp_path):
    from flightsim.sitl.flight_report import plot_flight
    from flightsim.worlds.world import load_world

    world = load_world(REPO / "flightsim" / "worlds" / "two-pillars.json")
    t = np.linspace(0.0, 10.0, 50)
    traj = np.column_stack(
        [t, -4.5 + 0.3 * t, 0.1 * t, np.full_like(t, 1.5), np.zeros_like(t), np.ones_like(t)]
    )
    fig = plot_flight(world, traj, engaged_at=4.0, collision_at=None, path=tmp_path / "f.png", title="t")
    fig.canvas.draw()  # laid out again at the figure's own dpi, where it is measured
    renderer = fig.canvas.get_renderer()
    ax = fig.axes[0]
    box = ax.get_legend().get_window_extent(renderer)
    assert not box.overlaps(ax.get_window_extent(renderer))  # not over the map
    assert box.x0 >= 0 and box.x1 <= fig.bbox.x1 and box.y0 >= 0 and box.y1 <= fig.bbox.y1


def test_height_is_judged_against_the_floor_and_the_rooms_height(capsys):
    """The true height while engaged: its range, and contact with the floor (the real PX4 flights
    went down to 0.45 m while the estimate said 1.4) or the ceiling, never left unjudged."""
    report = FlightReport.failed("rack", "external", "")
    report.judge_height(np.array([1.5, 0.6, 0.05, 1.2]), 3.0, "HIL_STATE_QUATERNION")
    assert (report.altitude_min_m, report.altitude_max_m) == (0.05, 1.5)
    assert report.floor_contact and not report.ceiling_contact
    print_report(report)
    assert "height 0.05-1.50 m in a 3.0 m room (judged on HIL_STATE_QUATERNION): FLOOR CONTACT" in (
        capsys.readouterr().out)
    high = FlightReport.failed("rack", "sim-ardupilot", "")
    high.judge_height(np.array([1.5, 2.95]), 3.0, "simulator")
    assert high.ceiling_contact and not high.floor_contact
    flown = FlightReport.failed("rack", "sim-ardupilot", "")
    flown.judge_height(np.array([0.45, 2.79]), 3.0, "SIM_STATE")
    assert not flown.floor_contact and not flown.ceiling_contact
    unflown = FlightReport.failed("rack", "sim-ardupilot", "")
    unflown.judge_height(np.zeros(0), 3.0, "simulator")
    assert unflown.altitude_min_m is None and not unflown.floor_contact
