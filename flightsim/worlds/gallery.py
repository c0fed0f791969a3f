"""``avoid-sim worlds``: look at the world families, and save generated worlds as JSON files.

``--gallery out.png`` draws one world per family (waypoints numbered, the planner's shortest safe
path dashed) so a person can see what each family asks of a pilot; ``--save DIR`` writes the same
worlds as world files for ``--world`` options elsewhere.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from companion.common.errors import UserError
from flightsim.worlds.families import ALL_FAMILIES, FAMILIES, generate_family_world
from flightsim.worlds.planner import shortest_safe_path
from flightsim.worlds.render import draw_top_down
from flightsim.worlds.world import DEFAULT_VEHICLE_RADIUS, World, save_world


def configure_parser(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--gallery", metavar="PNG", help="write one top-down panel per family to this PNG")
    parser.add_argument("--save", metavar="DIR", help="write each world as DIR/<name>.json")
    parser.add_argument(
        "--family", action="append", choices=ALL_FAMILIES,
        help="only this family (repeatable; default: every static family; the -dynamic ones have "
        "moving obstacles)",
    )  # fmt: skip
    parser.add_argument("--seed", type=int, default=0, help="generator seed (0)")
    parser.add_argument("--difficulty", type=float, default=0.5, help="0 (easy) … 1 (hard) (0.5)")
    parser.add_argument(
        "--radius", type=float, default=DEFAULT_VEHICLE_RADIUS, help="vehicle radius, metres (0.25)"
    )


def command(args: argparse.Namespace) -> int:
    if not 0.0 <= args.difficulty <= 1.0:
        raise UserError(f"--difficulty must be in [0, 1], got {args.difficulty}")
    if args.seed < 0:
        raise UserError(f"--seed must be non-negative, got {args.seed}")
    if not 0.05 <= args.radius <= 2.0:
        raise UserError(f"--radius must be in [0.05, 2] m, got {args.radius}")
    if not (args.gallery or args.save):
        raise UserError("nothing to do: give --gallery PNG and/or --save DIR")
    families = args.family or list(FAMILIES)
    worlds = [
        generate_family_world(f, args.seed, args.difficulty, vehicle_radius=args.radius) for f in families
    ]
    for world in worlds:
        moving = f"  {len(world.moving)} moving" if world.moving else ""
        print(f"{world.name:<22} {len(world.obstacles):>3} obstacles  {len(world.waypoints)} waypoints  "
              f"shortest safe path {world.shortest_path_m:.1f} m{moving}")  # fmt: skip
    if args.save:
        out = Path(args.save)
        try:
            out.mkdir(parents=True, exist_ok=True)
            for world in worlds:
                save_world(world, out / f"{world.name}.json")
        except OSError as exc:
            raise UserError(f"--save {out}: {exc.strerror}") from None
        print(f"saved {len(worlds)} worlds in {out}")
    if args.gallery:
        try:
            path = write_gallery(args.gallery, worlds, args.radius)
        except OSError as exc:
            raise UserError(f"--gallery {args.gallery}: {exc.strerror}") from None
        print(f"gallery: {path}")
    return 0


def write_gallery(path: str | Path, worlds: list[World], vehicle_radius: float, columns: int = 3) -> Path:
    """One panel per world with its waypoints and planned path; returns the PNG written."""
    columns = max(1, min(columns, len(worlds)))
    rows = math.ceil(len(worlds) / columns)
    fig = Figure(figsize=(5.0 * columns, 4.0 * rows), dpi=90)
    canvas = FigureCanvasAgg(fig)
    for i, world in enumerate(worlds):
        plan = shortest_safe_path(world, vehicle_radius=vehicle_radius)
        title = f"{world.name}: {len(world.waypoints)} waypoint(s), path {world.shortest_path_m:.1f} m"
        ax = fig.add_subplot(rows, columns, i + 1)
        draw_top_down(world, ax=ax, planned=None if plan is None else plan.points, title=title)
    fig.tight_layout()
    canvas.print_png(str(path))
    return Path(path)
