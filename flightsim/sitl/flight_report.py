"""The report of one SITL flight: its figures, the lines ``avoid-sim fly`` prints and its top-down PNG.

Apart from :mod:`flightsim.sitl.harness` (which runs the flight and fills a :class:`FlightReport` from what
it recorded) because reading, printing and drawing a flight's outcome needs no flight: the demo's
table, ``avoid-sim fly``'s output and the tests take a report (or a trajectory) as it is.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from flightsim.sitl.ground_station import MISSION_ACCEPTANCE_RADIUS
from flightsim.worlds.world import World

#: a vehicle's centre this near the floor touches it (landing gear), m
FLOOR_CONTACT_M = 0.1
#: ... and this near the room's height touches the ceiling (or leaves the room over the walls), m
CEILING_MARGIN_M = 0.1

#: ``FlightReport.error`` of a flight stopped by Ctrl-C (``avoid-sim fly`` then exits 130)
INTERRUPTED = "interrupted"


@dataclass
class FlightReport:
    """The outcome of one flight (JSON-serialisable)."""

    world: str
    autopilot: str
    engaged: bool
    collision: bool
    flight_time_s: float
    distance_m: float
    min_clearance_m: float | None  # None: nothing measured (the companion never flew)
    setpoint_rate_hz: float
    latency_p50_ms: float | None
    latency_p99_ms: float | None
    transitions: list[str]
    malformed: dict[str, int]
    plot: str = ""
    error: str = ""
    recording: str = ""
    waypoints_reached: list[tuple[int, float]] = field(default_factory=list)
    waypoints_total: int = 0
    items_reached: list[int] = field(default_factory=list)  # MISSION_ITEM_REACHED seqs the companion sent
    mission_complete: bool = False
    mission_time_s: float = -1.0
    goal_events: list[str] = field(default_factory=list)
    ground_truth: str = ""  # what collisions and clearance were judged on
    position_wait_s: float = 0.0  # external: how long the autopilot took to report a position, s
    altitude_truth: str = ""  # what the height was judged on (simulator, a truth message, estimate)
    altitude_min_m: float | None = None  # the height above the floor while engaged (None: not flown)
    altitude_max_m: float | None = None
    room_height_m: float = 0.0  # the room's walls' height (the ceiling a vehicle must stay under)
    floor_contact: bool = False  # while engaged the vehicle came within FLOOR_CONTACT_M of the floor
    ceiling_contact: bool = False  # ... or within CEILING_MARGIN_M of the room's height (or above it)
    warnings: list[str] = field(default_factory=list)

    def to_json(self) -> str:
        return json.dumps(dataclasses.asdict(self), indent=2)

    @classmethod
    def failed(cls, world: str, autopilot: str, error: str) -> FlightReport:
        """The report of a flight that could not start."""
        return cls(world, autopilot, False, False, 0.0, 0.0, None, 0.0, None, None, [], {}, error=error)

    def judge_height(self, heights: np.ndarray, room_height: float, source: str) -> None:
        """Fill the height figures from the true heights above the floor while engaged."""
        self.room_height_m = room_height
        self.altitude_truth = source
        if not len(heights):
            return
        self.altitude_min_m = round(float(np.min(heights)), 3)
        self.altitude_max_m = round(float(np.max(heights)), 3)
        self.floor_contact = self.altitude_min_m < FLOOR_CONTACT_M
        self.ceiling_contact = self.altitude_max_m > room_height - CEILING_MARGIN_M

    def title(self) -> str:
        """One line for the flight's picture: outcome, distance, clearance (and waypoints on a mission)."""
        outcome = "COLLISION" if self.collision else "no collision"
        clearance = measured(self.min_clearance_m, ".2f", "m")
        line = (f"{self.world} / {self.autopilot}: {outcome}, {self.distance_m:.1f} m, "
                f"min clearance {clearance}")
        if self.waypoints_total:
            line += f", waypoints {len(self.waypoints_reached)}/{self.waypoints_total}"
        return line


def measured(value: float | None, fmt: str, unit: str) -> str:
    """A report figure, or "n/a" when the flight measured none (never a -1 sentinel)."""
    return "n/a" if value is None else f"{value:{fmt}} {unit}"


def latency_ms(
    revolution_ends: list[float], setpoint_times: list[float], horizon: float = 0.3
) -> list[float]:
    """For each revolution end, the delay to the first setpoint that arrived after it (within ``horizon``)."""
    sp = np.asarray(sorted(setpoint_times))
    out = []
    for end in revolution_ends:
        i = int(np.searchsorted(sp, end))
        if i < len(sp) and sp[i] - end <= horizon:
            out.append(1000.0 * (sp[i] - end))
    return out


def waypoints_reached(world: World, traj: np.ndarray, engaged_at: float | None) -> list[tuple[int, float]]:
    """(waypoint index, seconds after engagement) of each waypoint reached in order (horizontally,
    within :data:`MISSION_ACCEPTANCE_RADIUS`), from the simulated vehicle's own trajectory."""
    out: list[tuple[int, float]] = []
    if engaged_at is None or not len(traj):
        return out
    i = 0
    for row in traj:
        if i == len(world.waypoints):
            break
        if math.dist(row[1:3], world.waypoints[i][:2]) <= MISSION_ACCEPTANCE_RADIUS:
            out.append((i, round(float(row[0] - engaged_at), 2)))
            i += 1
    return out


def plot_flight(
    world: World,
    traj: np.ndarray,
    engaged_at: float | None,
    collision_at: float | None,
    path: Path,
    title: str,
    world_t0: float | None = None,
) -> Any:
    """A top-down PNG (:func:`flightsim.worlds.render.draw_top_down`): the take-off and the companion's path,
    with a legend; returns the figure.

    :param traj: ``(N, 6)`` rows of (time, x, y, z, yaw, speed)
    :param world_t0: the time the world started at (its moving obstacles are drawn where they were
        at the last pose, with their trails); None: where they start
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from flightsim.worlds.render import draw_top_down

    if collision_at is not None and len(traj):
        traj = traj[traj[:, 0] <= collision_at]
    parts: list[np.ndarray] = [np.zeros((0, 2))]
    pose = None
    at = float(traj[-1, 0]) - world_t0 if world_t0 is not None and len(traj) else None
    if len(traj):
        flying = traj[:, 0] >= engaged_at if engaged_at is not None else np.zeros(len(traj), bool)
        parts = [traj[~flying, 1:3], traj[flying, 1:3]]  # take-off and hold first, then the companion
        pose = (traj[-1, 1:4], float(traj[-1, 4]))
    # constrained: the layout makes room for the legend beside the map
    fig = Figure(figsize=(9, 7 * world.room_size[1] / world.room_size[0] + 0.6), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    draw_top_down(
        world,
        parts,
        ax=ax,
        pose=pose,
        collided=collision_at is not None,
        title=title,
        labels=("take-off and hold (ground station)", "companion flying"),
        time=at,
    )
    fig.savefig(path, dpi=90)
    return fig


def print_report(r: FlightReport) -> None:
    """What ``avoid-sim fly`` prints after a flight."""
    print(f"world {r.world}, autopilot {r.autopilot}")
    if r.error:
        print(f"  error: {r.error}")
    for warning in r.warnings:
        print(f"  warning: {warning}")
    print(f"  engaged: {r.engaged}   collision: {r.collision}   flight {r.flight_time_s:.1f} s")
    clearance = measured(r.min_clearance_m, ".2f", "m")
    print(f"  distance flown {r.distance_m:.1f} m, minimum clearance {clearance} "
          f"(judged on {r.ground_truth or 'the simulator'})")
    print(
        f"  setpoints {r.setpoint_rate_hz:.1f} Hz, latency revolution end → setpoint "
        f"p50 {measured(r.latency_p50_ms, '.1f', 'ms')}, p99 {measured(r.latency_p99_ms, '.1f', 'ms')}"
    )
    if r.altitude_min_m is not None and r.altitude_max_m is not None:
        contact = [name for name, hit in (("FLOOR", r.floor_contact), ("CEILING", r.ceiling_contact)) if hit]
        print(f"  height {r.altitude_min_m:.2f}-{r.altitude_max_m:.2f} m in a {r.room_height_m:.1f} m room "
              f"(judged on {r.altitude_truth}){': ' + ' and '.join(contact) + ' CONTACT' if contact else ''}")
    print(f"  companion states: {' | '.join(r.transitions) or '-'}")
    if r.goal_events or r.waypoints_reached:
        reached = ", ".join(f"#{i + 1} at {t:.1f} s" for i, t in r.waypoints_reached) or "none"
        done = f"complete in {r.mission_time_s:.1f} s" if r.mission_complete else "not complete"
        count = f"{len(r.waypoints_reached)}/{r.waypoints_total}"
        print(f"  mission: waypoints reached {count} ({reached}); {done}")
        print(f"  companion goal: {' | '.join(r.goal_events) or '-'}")
        print(f"  companion MISSION_ITEM_REACHED: {', '.join(map(str, r.items_reached)) or '-'}")
    if r.plot:
        print(f"  plot: {r.plot}")
    if r.recording:
        print(f"  recording: {r.recording} (avoid-sim report / avoid-companion replay / Foxglove)")
