"""``avoid-sim report FILE.mcap``: the picture of a flight, drawn from its recording alone.

Time plots (speed, clearance, shield interventions, supervisor state) from what the companion
recorded, on the drone as in SITL; with ground truth (``avoid-sim fly`` recordings) also the
top-down picture of the room and the path flown, and the true speed and clearance.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.common.errors import UserError
from companion.recording import schemas as s
from companion.recording.reader import Recording, read_recording, setpoints
from companion.safety.shield import sector_bins
from flightsim.sitl.recording import TRUTH_METADATA, TRUTH_STATE
from flightsim.worlds.world import DEFAULT_VEHICLE_RADIUS, World, world_from_dict

STATES = ("STARTING", "WAITING_FOR_AUTOPILOT", "STANDBY", "PILOT_OVERRIDE", "HOLD", "ACTIVE")


@dataclass
class FlightSeries:
    """The time series a report draws, seconds since the recording's first message."""

    t0: float
    # t, forward, yaw rate, vertical (climb, NaN: not recorded)
    setpoint: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    requested: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  # t, forward asked by policy
    scan_clearance: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # t, front, nearest
    interventions: dict[str, list[float]] = field(default_factory=dict)  # limit -> times
    states: list[tuple[float, str]] = field(default_factory=list)  # (t, new state)
    truth: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))  # t, x, y, z, speed, clearance
    world: World | None = None


def flight_series(rec: Recording) -> FlightSeries:
    """Everything the report draws, from the recording's messages."""
    times = [rows[0][0] for rows in rec.messages.values() if rows]
    if not times:
        raise UserError(f"{rec.path}: the recording holds no messages")
    t0 = min(times)
    out = FlightSeries(t0)
    sent = setpoints(rec)
    out.setpoint = np.column_stack([sent[:, 0] - t0, sent[:, 1], sent[:, 2], sent[:, 4]])
    shield = rec.topic(s.SHIELD.topic)
    out.requested = np.array([(t - t0, msg["requested"]["forward"]) for t, msg in shield]).reshape(-1, 2)
    for t, msg in shield:
        for name in msg["limits"]:
            out.interventions.setdefault(name, []).append(t - t0)
    scans = rec.topic(s.SCAN.topic)
    if scans:
        front = sector_bins(0.0, 30.0)
        rows = []
        for t, msg in scans:
            ranges = np.asarray(msg["ranges"])
            rows.append((t - t0, ranges[front].min(), ranges.min()))
        out.scan_clearance = np.array(rows)
    out.states = [(t - t0, msg["new"]) for t, msg in rec.topic(s.TRANSITION.topic)]
    truth = rec.topic(TRUTH_STATE.topic)
    out.truth = np.array([
        (t - t0, m["position"]["x"], m["position"]["y"], m["position"]["z"], m["speed"],
         np.nan if m["clearance"] is None else m["clearance"]) for t, m in truth
    ]).reshape(-1, 6)
    meta = rec.metadata.get(TRUTH_METADATA)
    if meta and "world" in meta:
        out.world = world_from_dict(json.loads(meta["world"]), path_for_messages=f"{rec.path} (world)")
    return out


def summary(series: FlightSeries) -> list[str]:
    """A few lines of text beside the picture."""
    lines = []
    end = max([series.setpoint[-1, 0] if len(series.setpoint) else 0.0,
               series.scan_clearance[-1, 0] if len(series.scan_clearance) else 0.0,
               series.truth[-1, 0] if len(series.truth) else 0.0])
    n_scans, n_setpoints = len(series.scan_clearance), len(series.setpoint)
    lines.append(f"{end:.1f} s recorded, {n_scans} scans, {n_setpoints} setpoints")
    vertical = series.setpoint[:, 3]
    if len(vertical) and np.isnan(vertical).all():
        lines.append("vertical setpoint: not recorded (a recording made before it was)")
    elif len(vertical):
        lines.append(f"vertical setpoint: climb up to {max(np.nanmax(vertical), 0.0):.2f} m/s, "
                     f"descent up to {max(-np.nanmin(vertical), 0.0):.2f} m/s")
    if series.interventions:
        lines.append("shield limits acted: " + ", ".join(
            f"{k} {len(v)}" for k, v in sorted(series.interventions.items())))
    if len(series.truth):
        clear = series.truth[:, 5][series.truth[:, 3] > 0.3]
        if len(clear) and np.isfinite(clear).any():
            lines.append(f"true minimum clearance {np.nanmin(clear):.2f} m")
    lines.append("states: " + (" → ".join(state for _, state in series.states) or "-"))
    return lines


def draw_report(series: FlightSeries, path: Path, title: str) -> None:
    """Top-down picture (with ground truth) left, time plots right; one PNG."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from flightsim.worlds.render import draw_top_down

    has_map = series.world is not None and len(series.truth) > 0
    fig = Figure(figsize=(15 if has_map else 10, 9))
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(4, 2 if has_map else 1, width_ratios=[1, 1.3] if has_map else None)
    col = 1 if has_map else 0
    axes = [fig.add_subplot(grid[0, col])]
    axes += [fig.add_subplot(grid[i, col], sharex=axes[0]) for i in (1, 2, 3)]
    if has_map:
        assert series.world is not None
        traj = series.truth
        active_from = next((t for t, state in series.states if state == "ACTIVE"), None)
        flying = traj[:, 0] >= active_from if active_from is not None else np.zeros(len(traj), bool)
        collided = bool(np.nanmin(np.where(traj[:, 3] > 0.3, traj[:, 5], np.inf)) < DEFAULT_VEHICLE_RADIUS)
        draw_top_down(series.world, [traj[~flying, 1:3], traj[flying, 1:3]], ax=fig.add_subplot(grid[:, 0]),
                      collided=collided, title=f"{series.world.name}: take-off, then the companion")
    _speed(axes[0], series)
    _clearance(axes[1], series)
    _interventions(axes[2], series)
    _states(axes[3], series)
    axes[3].set_xlabel("time since the recording started, s")
    for ax in axes[:3]:
        ax.tick_params(labelbottom=False)
    fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=80)


def _speed(ax: Any, f: FlightSeries) -> None:
    if len(f.requested):
        ax.plot(f.requested[:, 0], f.requested[:, 1], color="tab:orange", lw=1, alpha=0.8,
                label="policy asked")
    if len(f.setpoint):
        ax.step(f.setpoint[:, 0], f.setpoint[:, 1], where="post", color="tab:blue", lw=1.2,
                label="setpoint sent")
        if not np.isnan(f.setpoint[:, 3]).all():
            ax.step(f.setpoint[:, 0], f.setpoint[:, 3], where="post", color="tab:green", lw=1,
                    label="vertical sent (up)")
    if len(f.truth):
        ax.plot(f.truth[:, 0], f.truth[:, 4], color="black", lw=1, label="true speed")
    ax.set_ylabel("speed, m/s")
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right", fontsize=8)


def _clearance(ax: Any, f: FlightSeries) -> None:
    if len(f.scan_clearance):
        ax.plot(f.scan_clearance[:, 0], f.scan_clearance[:, 1], color="tab:red", lw=1,
                label="scan, front ±30°")
        ax.plot(f.scan_clearance[:, 0], f.scan_clearance[:, 2], color="tab:purple", lw=0.8, alpha=0.7,
                label="scan, nearest")
    if len(f.truth):
        airborne = f.truth[:, 3] > 0.3
        ax.plot(f.truth[airborne, 0], f.truth[airborne, 5], color="black", lw=1, label="true clearance")
    ax.set_ylabel("clearance, m")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper right", fontsize=8)


def _interventions(ax: Any, f: FlightSeries) -> None:
    names = sorted(f.interventions)
    for i, name in enumerate(names):
        ax.plot(f.interventions[name], [i] * len(f.interventions[name]), "|", ms=10, mew=1.5)
    ax.set_yticks(range(len(names)), names, fontsize=8)
    ax.set_ylim(-0.7, max(len(names), 1) - 0.3)
    ax.set_ylabel("shield")
    ax.grid(alpha=0.3, axis="x")
    if not names:
        ax.text(0.5, 0.5, "no shield intervention", transform=ax.transAxes, ha="center", va="center")


def _states(ax: Any, f: FlightSeries) -> None:
    if f.states:
        level = {name: i for i, name in enumerate(STATES)}
        t = [t for t, _ in f.states]
        y = [level.get(state, 0) for _, state in f.states]
        end = max([t[-1]] + ([f.setpoint[-1, 0]] if len(f.setpoint) else [])
                  + ([f.scan_clearance[-1, 0]] if len(f.scan_clearance) else []))
        ax.step([*t, end], [*y, y[-1]], where="post", color="tab:green")
    ax.set_yticks(range(len(STATES)), STATES, fontsize=7)
    ax.set_ylabel("supervisor")
    ax.grid(alpha=0.3)


def configure_parser(parser: argparse.ArgumentParser) -> None:
    """``report FILE.mcap [--out PNG]``."""
    parser.add_argument("recording", metavar="FILE.mcap", help="a flight recording")
    parser.add_argument("--out", metavar="PNG", help="picture to write (default: <recording>.report.png)")


def command(args: argparse.Namespace) -> int:
    path = Path(args.recording)
    rec = read_recording(path)
    series = flight_series(rec)
    out = Path(args.out) if args.out else path.with_suffix(".report.png")
    draw_report(series, out, f"{path.name}" + (" (ends early: not closed)" if rec.truncated else ""))
    for line in summary(series):
        print(line)
    print(f"picture: {out}")
    return 0
