"""Top-down pictures of worlds and flights (matplotlib Agg; no display, no pyplot state).

:func:`draw_top_down` draws one world with its trajectories (and optionally the vehicle and its
current scan) onto an Axes; :func:`render_rgb` returns that as an RGB array for the environment's
``rgb_array`` mode; :func:`plot_worlds` writes several panels to a PNG for flight and evaluation
reports.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from matplotlib.patches import Circle, Polygon, Rectangle

from flightsim.worlds.moving import MovingObstacle
from flightsim.worlds.world import WALL_THICKNESS, Box, World

_WALL = "#303030"
_OBSTACLE = "#8c8c8c"
_OBSTACLE_EDGE = "#404040"
_LOW_OBSTACLE = "#e3e3e3"
_FLOATING = "#b0b0b0"
_RAY = "#e4572e"
_FREE_RAY = "#e6e6e6"
_VEHICLE = "#1f5fbf"
_WAYPOINT = "#2a9d3f"
_WAYPOINT_ACTIVE = "#e08a00"
_PLANNED = "#555555"
_MOVING = "#8e44ad"
TRACK_PREVIEW_S = 10.0  # a world's picture without a time shows where its movers go in this long
_TRAJECTORY_COLOURS = ("#1f77b4", "#2ca02c", "#9467bd", "#ff7f0e", "#17becf", "#8c564b", "#e377c2")


def _box_corners(box: Box) -> np.ndarray:
    c, s = math.cos(math.radians(box.yaw_deg)), math.sin(math.radians(box.yaw_deg))
    hx, hy = box.size[0] / 2.0, box.size[1] / 2.0
    local = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    return local @ np.array([[c, s], [-s, c]]) + np.asarray(box.center[:2])


def draw_top_down(
    world: World,
    trajectories: np.ndarray | Sequence[np.ndarray] = (),
    *,
    ax: Axes | None = None,
    scan: np.ndarray | None = None,
    pose: tuple[np.ndarray, float] | None = None,
    scan_max_range: float = 10.0,
    vehicle_radius: float = 0.25,
    collided: bool = False,
    title: str | None = None,
    active_waypoint: int | None = None,
    planned: np.ndarray | None = None,
    labels: Sequence[str] | None = None,
    time: float | None = None,
) -> Axes:
    """Draw a world seen from above: walls, obstacles, start, waypoints, trajectories, vehicle, scan.

    Obstacles whose top is below the start altitude by more than the vehicle's radius (flown over)
    are drawn light with a dashed edge; obstacles that do not stand on the floor (beams) hatched.

    :param world: the room and its obstacles
    :param trajectories: one ``(N, 2|3)`` array of positions or a sequence of them (each its own
        colour; a dot marks where each ended)
    :param ax: where to draw (a new figure's Axes if None)
    :param scan: ``(360,)`` normalised scan drawn as rays from the vehicle (needs ``pose``); bin
        ``i`` points ``i`` degrees counter-clockwise from the nose; bins with a return are drawn
        strong up to the hit, empty bins faint to the scan's range
    :param pose: the vehicle's ``(position, yaw_rad)``, drawn as a disc with a heading arrow
    :param scan_max_range: metres that a scan value of 1.0 stands for
    :param vehicle_radius: disc radius, metres
    :param collided: draw the vehicle in red with a cross
    :param title: axes title
    :param active_waypoint: index of the waypoint being flown to, drawn larger in another colour
        (waypoints before it faded: already reached)
    :param planned: ``(N, 2)`` planned path (e.g. :attr:`flightsim.worlds.planner.PlannedPath.points`),
        drawn dashed
    :param time: seconds since the start: each moving obstacle is drawn where it is then, with its
        trail from the start; None: where it starts, with its track over the next 10 s dotted
    :param labels: one name per trajectory; given, the Axes gets a legend (start, each trajectory,
        the vehicle, a collision) so the picture reads on its own
    :return: the Axes drawn on
    """
    if ax is None:
        ax = Figure(figsize=(6, 5)).add_subplot()
    hx, hy = world.room_size[0] / 2.0, world.room_size[1] / 2.0
    t = WALL_THICKNESS
    ax.add_patch(Rectangle((-hx - t, -hy - t), 2 * (hx + t), 2 * (hy + t), color=_WALL, zorder=0))
    ax.add_patch(Rectangle((-hx, -hy), 2 * hx, 2 * hy, color="white", zorder=0))
    altitude = world.start_position[2]
    for obstacle in world.obstacles:
        if isinstance(obstacle, Box):
            patch = Polygon(_box_corners(obstacle), closed=True)
            bottom, top = obstacle.center[2] - obstacle.size[2] / 2, obstacle.center[2] + obstacle.size[2] / 2
        else:
            patch = Circle(obstacle.center, obstacle.radius)
            bottom, top = 0.0, obstacle.height
        patch.set(facecolor=_OBSTACLE, edgecolor=_OBSTACLE_EDGE, linewidth=0.8, zorder=2)
        if top < altitude - vehicle_radius:  # below the flight altitude: flown over
            patch.set(facecolor=_LOW_OBSTACLE, linestyle="--", zorder=1)
        elif bottom > 0.05:  # floating (a beam): hatched
            patch.set(facecolor=_FLOATING, hatch="////")
        ax.add_patch(patch)
    for mover in world.moving:
        _draw_moving(ax, mover, time)
    sx, sy, _ = world.start_position
    yaw0 = math.radians(world.start_yaw_deg)
    start_style = {"marker": "o", "markersize": 5, "markerfacecolor": "none", "linestyle": "none"}
    ax.plot([sx], [sy], color="black", zorder=3, label="start (arrow: heading)", **start_style)
    ax.annotate(
        "", xy=(sx + 0.8 * math.cos(yaw0), sy + 0.8 * math.sin(yaw0)), xytext=(sx, sy),
        arrowprops={"arrowstyle": "->", "color": "black", "lw": 1.0}, zorder=3,
    )  # fmt: skip

    _draw_waypoints(ax, world, active_waypoint)
    if planned is not None and len(planned) > 1:
        planned = np.asarray(planned, dtype=float)
        ax.plot(planned[:, 0], planned[:, 1], color=_PLANNED, linestyle="--", linewidth=1.0, zorder=3)

    if isinstance(trajectories, np.ndarray):
        trajectories = [trajectories]
    for i, traj in enumerate(trajectories):
        traj = np.asarray(traj, dtype=float)
        if traj.ndim != 2 or traj.shape[0] == 0:
            continue
        colour = _TRAJECTORY_COLOURS[i % len(_TRAJECTORY_COLOURS)]
        label = labels[i] if labels is not None and i < len(labels) else None
        ax.plot(traj[:, 0], traj[:, 1], color=colour, linewidth=1.4, zorder=4, label=label)
        ax.plot(traj[-1:, 0], traj[-1:, 1], marker="o", markersize=3.5, color=colour, zorder=4)

    if pose is not None:
        position, yaw = np.asarray(pose[0], dtype=float), float(pose[1])
        px, py = position[0], position[1]
        if scan is not None:
            _draw_scan(ax, np.asarray(scan, dtype=float), px, py, yaw, scan_max_range)
        colour = "#d62728" if collided else _VEHICLE
        ax.add_patch(
            Circle(
                (px, py),
                vehicle_radius,
                facecolor=colour,
                edgecolor="black",
                lw=0.8,
                zorder=6,
                label="vehicle",
            )
        )
        nose = max(3.0 * vehicle_radius, 0.5)
        tip = (px + nose * math.cos(yaw), py + nose * math.sin(yaw))
        ax.plot([px, tip[0]], [py, tip[1]], color="black", lw=2.0, zorder=7)
        if collided:
            ax.plot(
                [px], [py], marker="x", markersize=14, mew=3, color="#d62728", zorder=8, label="collision"
            )

    ax.set_xlim(-hx - 0.5, hx + 0.5)
    ax.set_ylim(-hy - 0.5, hy + 0.5)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.tick_params(labelsize=7)
    if title:
        ax.set_title(title, fontsize=9)
    if labels is not None:  # beside the map, never over it
        ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0, fontsize=7)
    return ax


def _draw_moving(ax: Axes, mover: MovingObstacle, time: float | None) -> None:
    """Its outline (hatched in the movers' colour) at ``time`` and its trail up to then, or where
    it starts and its track ahead."""
    until = TRACK_PREVIEW_S if time is None else max(float(time), 0.0)
    samples = max(2, min(2000, int(until * 20) + 1))
    trail = mover.positions(np.linspace(0.0, until, samples))
    ax.plot(
        trail[:, 0], trail[:, 1], color=_MOVING, linewidth=1.2, zorder=2,
        linestyle=":" if time is None else "-",
    )  # fmt: skip
    x, y = trail[0] if time is None else trail[-1]
    if mover.shape == "cylinder":
        patch = Circle((x, y), mover.radius)
    else:
        patch = Polygon(
            _box_corners(Box((x, y, 0.0), (*mover.size, mover.height), mover.yaw_deg)), closed=True
        )
    patch.set(facecolor="#d7bde2", edgecolor=_MOVING, linewidth=1.0, hatch="....", zorder=3)
    ax.add_patch(patch)


def _draw_waypoints(ax: Axes, world: World, active: int | None) -> None:
    """Numbered discs in visiting order; the active one highlighted, those before it faded."""
    for i, (x, y, _) in enumerate(world.waypoints):
        is_active = active == i
        done = active is not None and i < active
        colour = _WAYPOINT_ACTIVE if is_active else _WAYPOINT
        ax.plot(
            [x], [y], marker="o", markersize=13 if is_active else 10, color=colour,
            alpha=0.35 if done else 1.0, markeredgecolor="black", markeredgewidth=0.6, zorder=3,
        )  # fmt: skip
        ax.annotate(
            str(i + 1), (x, y), ha="center", va="center", fontsize=7, color="white",
            fontweight="bold", zorder=3,
        )  # fmt: skip


def _draw_scan(ax: Axes, scan: np.ndarray, px: float, py: float, yaw: float, max_range: float) -> None:
    angles = yaw + np.radians(np.arange(scan.size) + 0.5)  # bin centres, counter-clockwise from the nose
    ends = np.stack([px + scan * max_range * np.cos(angles), py + scan * max_range * np.sin(angles)], axis=1)
    start = np.broadcast_to([px, py], ends.shape)
    segments = np.stack([start, ends], axis=1)
    hit = scan < 1.0
    ax.add_collection(LineCollection(segments[~hit], colors=_FREE_RAY, linewidths=0.4, zorder=1))
    ax.add_collection(LineCollection(segments[hit], colors=_RAY, linewidths=0.5, alpha=0.6, zorder=5))
    ax.plot(ends[hit, 0], ends[hit, 1], linestyle="none", marker=".", markersize=2.0, color=_RAY, zorder=5)


def render_rgb(
    world: World,
    trajectory: np.ndarray,
    *,
    scan: np.ndarray | None = None,
    pose: tuple[np.ndarray, float] | None = None,
    scan_max_range: float = 10.0,
    vehicle_radius: float = 0.25,
    collided: bool = False,
    title: str | None = None,
    width_px: int = 720,
    active_waypoint: int | None = None,
    time: float | None = None,
) -> np.ndarray:
    """The :func:`draw_top_down` picture as an ``(H, W, 3)`` uint8 array.

    :param width_px: image width; the height follows the room's aspect ratio
    :param active_waypoint: see :func:`draw_top_down`
    :param time: see :func:`draw_top_down`
    """
    sx, sy = world.room_size[0] + 1.0, world.room_size[1] + 1.0
    dpi = 100
    width_in = width_px / dpi
    height_in = min(max(width_in * sy / sx + 0.6, 2.5), 2.0 * width_in)
    fig = Figure(figsize=(width_in, height_in), dpi=dpi)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    draw_top_down(
        world, trajectory, ax=ax, scan=scan, pose=pose, scan_max_range=scan_max_range,
        vehicle_radius=vehicle_radius, collided=collided, title=title, active_waypoint=active_waypoint,
        time=time,
    )  # fmt: skip
    fig.tight_layout()
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def plot_worlds(
    path: str | Path,
    panels: Sequence[tuple[World, Sequence[np.ndarray], str]],
    *,
    columns: int = 3,
    panel_size: tuple[float, float] = (5.0, 4.0),
) -> Path:
    """Write a PNG of several worlds, each with its trajectories and a title.

    :param path: PNG file to write
    :param panels: ``(world, [trajectory, ...], title)`` per panel
    :param columns: panels per row
    :param panel_size: inches per panel (width, height)
    :return: the path written
    """
    if not panels:
        raise ValueError("plot_worlds needs at least one panel")
    columns = max(1, min(columns, len(panels)))
    rows = math.ceil(len(panels) / columns)
    fig = Figure(figsize=(panel_size[0] * columns, panel_size[1] * rows), dpi=100)
    canvas = FigureCanvasAgg(fig)
    for i, (world, trajectories, title) in enumerate(panels):
        draw_top_down(world, list(trajectories), ax=fig.add_subplot(rows, columns, i + 1), title=title)
    fig.tight_layout()
    path = Path(path)
    canvas.print_png(str(path))
    return path
