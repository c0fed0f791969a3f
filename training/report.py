"""The evaluation's figures: per controller, overall, per world and per family (the goal task),
as a JSON-able report, a text table and a picture of the trajectories over each world.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from companion.safety.shield import ShieldConfig
from flightsim.envs.env import MOVER_STEADY_WINDOW_S
from training.config import NEAR_MISS_DISTANCE, SUCCESS_MIN_MEAN_SPEED
from training.episodes import EpisodeResult, WorldSpec

#: the movers' speed the shield's promise assumes, m/s: a collision with a faster one is outside it
MOVER_SPEED_BOUND = ShieldConfig().mover_speed


def summarise(results: Sequence[EpisodeResult]) -> dict[str, Any]:
    """Success rate, collisions, mean distance and speed, worst clearance and near misses of ``results``
    (and for the goal task :func:`goal_summary`'s figures too)."""
    n = len(results)
    if n == 0:
        return {"episodes": 0}
    if any(r.waypoints for r in results):
        return goal_summary(results)
    return {
        "episodes": n,
        "success_rate": sum(r.success for r in results) / n,
        "collisions": sum(r.collision for r in results),
        "mean_distance_m": float(np.mean([r.distance for r in results])),
        "mean_speed_mps": float(np.mean([r.mean_speed for r in results])),
        "min_clearance_m": float(min(r.min_clearance for r in results)),
        "near_misses": sum(r.near_misses for r in results),
    }


def goal_summary(results: Sequence[EpisodeResult]) -> dict[str, Any]:
    """The goal task's figures: success, collision and timeout rates, mean time to goal and SPL (the
    last two over successes only; ``spl_all`` counts a failure as 0, as Anderson et al. define it)."""
    n = len(results)
    won = [r for r in results if r.success]
    spl = [r.shortest_path_m / max(r.distance, r.shortest_path_m, 1e-9) for r in won]
    hit = [r for r in results if r.collision_mover_speed is not None]
    within = [r for r in hit if r.collision_mover_speed <= MOVER_SPEED_BOUND]
    return {
        "episodes": n,
        "success_rate": len(won) / n,
        "collision_rate": sum(r.collision for r in results) / n,
        "timeout_rate": sum(r.timeout for r in results) / n,
        "mean_time_s": float(np.mean([r.time_s for r in won])) if won else None,
        "spl": float(np.mean(spl)) if won else None,
        "spl_all": float(np.sum(spl)) / n,
        "waypoints_reached": sum(r.waypoints_reached for r in results)
        / max(sum(r.waypoints for r in results), 1),
        "collisions": sum(r.collision for r in results),
        "mover_collisions": len(hit),
        "mover_collisions_within_bound": len(within),
        "mover_collisions_within_model": sum(
            r.collision_mover_steady_s >= MOVER_STEADY_WINDOW_S for r in within
        ),
        "mean_distance_m": float(np.mean([r.distance for r in results])),
        "min_clearance_m": float(min(r.min_clearance for r in results)),
        "near_misses": sum(r.near_misses for r in results),
    }


def report(results: Sequence[EpisodeResult], worlds: Sequence[WorldSpec]) -> dict[str, Any]:
    """The evaluation as a JSON-able dict: per controller, overall and per world, plus every episode."""
    controllers = list(dict.fromkeys(r.controller for r in results))
    goal = any(r.waypoints for r in results)
    out: dict[str, Any] = {
        "success_definition": (
            "every waypoint reached in order, no collision, within the world's time limit; "
            "mean_time_s and spl over successes only"
            if goal
            else f"no collision for max_steps and mean speed >= {SUCCESS_MIN_MEAN_SPEED} m/s "
            f"(40 m over the default 100 s)"
        )
        + f"; near miss: clearance < {NEAR_MISS_DISTANCE} m",
        "worlds": [asdict(w) for w in worlds],
        "controllers": {},
    }
    for c in controllers:
        mine = [r for r in results if r.controller == c]
        out["controllers"][c] = {
            "overall": summarise(mine),
            "per_world": {w.name: summarise([r for r in mine if r.world == w.name]) for w in worlds},
        }
        if goal:
            out["controllers"][c]["per_family"] = summarise_by(mine, lambda r: r.family)
            by_response = summarise_by(mine, lambda r: r.response.get("name", "ideal"))
            if len(by_response) > 1:  # with ``random``: each firmware structure drawn
                out["controllers"][c]["per_response"] = dict(sorted(by_response.items()))
    out["episodes"] = [{k: v for k, v in asdict(r).items() if k != "trajectory"} for r in results]
    return out


def summarise_by(results: Sequence[EpisodeResult], key: Callable[[EpisodeResult], str]) -> dict[str, Any]:
    """:func:`summarise` per value of ``key`` (a family, the response flown), in first-seen order.

    The response's name splits ``random`` draws by firmware structure (``random-px4``,
    ``random-ardupilot``), which fail differently behind the shield.
    """
    return {k: summarise([r for r in results if key(r) == k]) for k in dict.fromkeys(key(r) for r in results)}


def format_table(summary: dict[str, Any], per_world: bool) -> str:
    """A readable text table of :func:`report`'s output."""
    if any("per_family" in data for data in summary["controllers"].values()):
        return format_goal_table(summary, per_world)
    header = f"{'controller':<19} {'world':<16} {'eps':>4} {'success':>8} {'coll':>5} {'dist m':>8} "
    header += f"{'speed':>6} {'min clr':>8} {'near':>5}"
    lines = [header, "-" * len(header)]

    def row(name: str, world: str, s: dict[str, Any]) -> str:
        return (
            f"{name:<19} {world:<16} {s['episodes']:>4} {100 * s['success_rate']:>7.1f}% "
            f"{s['collisions']:>5} {s['mean_distance_m']:>8.1f} {s['mean_speed_mps']:>6.2f} "
            f"{s['min_clearance_m']:>8.2f} {s['near_misses']:>5}"
        )

    for name, data in summary["controllers"].items():
        if per_world:
            for world, s in data["per_world"].items():
                lines.append(row(name, world, s))
        lines.append(row(name, "ALL", data["overall"]))
    return "\n".join(lines)


#: the usual colour of each controller; a "+shield" variant keeps it unless its unshielded self is
#: in the same picture, and any other controller takes the next free colour of the palette
CONTROLLER_COLOURS = {"policy": "tab:blue", "gap_follower": "tab:orange", "random": "tab:gray"}
PALETTE = ("tab:green", "tab:purple", "tab:brown", "tab:pink", "tab:olive", "tab:cyan", "navy", "black")


def controller_colours(names: Iterable[str]) -> dict[str, str]:
    """A distinct colour for every controller label (``policy``, ``policy+shield``, custom names)."""
    labels = sorted(set(names), key=lambda n: (n.endswith("+shield"), n))  # unshielded ones choose first
    colours: dict[str, str] = {}
    for label in labels:
        preferred = CONTROLLER_COLOURS.get(label.removesuffix("+shield"))
        free = [c for c in (preferred, *PALETTE) if c is not None and c not in colours.values()]
        colours[label] = free[0] if free else f"C{len(colours) % 10}"
    return colours


def format_goal_table(summary: dict[str, Any], per_world: bool) -> str:
    """The goal task's table: a row per family (and per world with ``per_world``), per response
    structure when more than one was flown, then overall."""
    header = f"{'controller':<22} {'family/world':<24} {'eps':>4} {'success':>8} {'coll':>6} {'timeout':>8} "
    header += f"{'time s':>7} {'SPL':>5} {'min clr':>8}"
    lines = [header, "-" * len(header)]

    def row(name: str, where: str, s: dict[str, Any]) -> str:
        time_s = "-" if s["mean_time_s"] is None else f"{s['mean_time_s']:.1f}"
        spl = "-" if s["spl"] is None else f"{s['spl']:.2f}"
        return (
            f"{name:<22} {where:<24} {s['episodes']:>4} {100 * s['success_rate']:>7.1f}% "
            f"{100 * s['collision_rate']:>5.1f}% {100 * s['timeout_rate']:>7.1f}% {time_s:>7} {spl:>5} "
            f"{s['min_clearance_m']:>8.2f}"
        )

    for name, data in summary["controllers"].items():
        if per_world:
            lines += [row(name, world, s) for world, s in data["per_world"].items()]
        lines += [row(name, family, s) for family, s in data["per_family"].items()]
        lines += [row(name, f"resp. {response}", s) for response, s in data.get("per_response", {}).items()]
        lines.append(row(name, "ALL", data["overall"]))
        hit = data["overall"]
        if hit["mover_collisions"]:
            within, steady = hit["mover_collisions_within_bound"], hit["mover_collisions_within_model"]
            where = (
                f"{within} at most {MOVER_SPEED_BOUND:g} m/s, the shield's mover_speed; {steady} of them "
                f"also kept their velocity for the {MOVER_STEADY_WINDOW_S:g} s before"
            )
            lines.append(f"{name:<22} {'hit a mover':<24} {hit['mover_collisions']:>4} ({where})")
    return "\n".join(lines)


#: the evaluation PNG's legend at 9 pt: inches a label's character, a handle with its gaps, a row takes
LEGEND_CHAR_IN = 0.075
LEGEND_HANDLE_IN = 0.7
LEGEND_ROW_IN = 0.25


def plot_trajectories(
    results: Sequence[EpisodeResult], worlds: Sequence[WorldSpec], out: Path, env_config: Any
) -> None:
    """Write :func:`trajectory_figure` as a PNG."""
    fig = trajectory_figure(results, worlds, env_config)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(str(out), dpi=100 if len(worlds) <= 16 else 50)  # a 100-world grid stays ~1 MB


def trajectory_figure(results: Sequence[EpisodeResult], worlds: Sequence[WorldSpec], env_config: Any) -> Any:
    """One panel per world (drawn by :func:`flightsim.worlds.render.draw_top_down`), each controller's first
    episode over it in its own colour (:func:`controller_colours`), one legend for all; a red cross
    marks a collision."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from flightsim.worlds.render import draw_top_down

    colours = controller_colours(r.controller for r in results)
    cols = min(len(worlds), 10 if len(worlds) > 16 else 4)
    rows = math.ceil(len(worlds) / cols)
    fig = Figure(figsize=(2.8 * cols, 2.4 * rows + 0.6))
    FigureCanvasAgg(fig)  # attaches itself to the figure: no pyplot state in worker processes
    legend: dict[str, Any] = {}
    for i, w in enumerate(worlds):
        ax = fig.add_subplot(rows, cols, i + 1)
        radius = env_config.vehicle_radius
        draw_top_down(w.world(radius), ax=ax, vehicle_radius=radius)
        for r in results:
            if r.world != w.name or r.episode != 0:
                continue
            xy = np.asarray(r.trajectory)
            (line,) = ax.plot(xy[:, 0], xy[:, 1], lw=0.9, color=colours[r.controller], zorder=5)
            legend.setdefault(r.controller, line)
            if r.collision:
                ax.plot(xy[-1, 0], xy[-1, 1], "x", color="red", ms=7, mew=2, zorder=6)
        ax.set_title(w.name, fontsize=8)
        ax.set_xlabel("")
        ax.set_ylabel("")
        ax.tick_params(labelsize=5)
    from matplotlib.lines import Line2D

    labels = sorted(legend)
    handles = [legend[n] for n in labels]
    handles.append(Line2D([], [], color="red", marker="x", ls="none", mew=2))
    labels = [*labels, "collision"]
    # below the panels, never over a map: as many entries a row as the figure's width holds
    entry = max(LEGEND_CHAR_IN * len(label) + LEGEND_HANDLE_IN for label in labels)
    ncol = max(1, min(len(labels), int(fig.get_figwidth() // entry)))
    rows_needed = math.ceil(len(labels) / ncol)
    fig.set_figheight(fig.get_figheight() + LEGEND_ROW_IN * (rows_needed - 1))
    fig.legend(handles, labels, loc="lower center", ncol=ncol, fontsize=9, frameon=False)
    fig.tight_layout(rect=(0, (LEGEND_ROW_IN * rows_needed + 0.2) / fig.get_figheight(), 1, 1))
    return fig
