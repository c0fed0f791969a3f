"""Figures: controllers that want to crash, flown behind today's shield and behind the backup gate.

Each attacker (:mod:`training.attackers`: ram, dash, held_random) and, with ``--policy``, the
policy itself fly LidarNav-v0 over every world family, a random firmware response per episode,
behind the shield's rules alone and behind the rules with the backup gate, on the same worlds and
seeds in the same run. Prints per attacker and shield: episodes, collisions, and the collisions
of the episodes the gate's promise covers out of those episodes (``promised``: the gate never
reduced to best effort, its sign that the invariant was lost: a start too close, the creep after a
stop that an envelope without a position loop allows, or a velocity error beyond the envelope's,
which the simulator's unbounded random walk may reach); then the least clearance (m, from the
vehicle centre; a collision is below 0.25) and the worst episode, with the largest difference of
the velocity the shield judged by from the true one (the measurement's lag in hard accelerations
included, which the envelope covers by its delay window).

    python bench/bench_shield_attack.py [--seeds 4] [--first-seed 599000] [--max-steps 400]
        [--workers 2] [--policy models/policy.onnx]

With ``--out FILE`` (JSON lines), the seeds are flown in chunks of ``--chunk`` per family, each
chunk appended to the file as it finishes, and a chunk the file already holds is not flown again;
the figures are then those of every episode in the file. So a run of ``--episodes`` episodes
behind the gate (10,000: several hours on two cores) can stop and resume, across sessions:

    python bench/bench_shield_attack.py --out runs/attack.jsonl --episodes 10000 --max-steps 200

``--autopilot-response ardupilot`` flies ArduPilot's calibrated response instead of the random draw,
and the gate assumes its envelope (the position loop's, with narrower corridors).

With ``--search``, instead the search-based attacker (:mod:`training.attack_search`: a command
sequence optimised by the cross-entropy method, each candidate flown) attacks one world of each
family in ``--worlds`` (seed ``--first-seed``, difficulty ``--difficulty``) behind the rules and
behind the gate; per world it prints the least clearance and whether the worst sequence collided,
then the episodes flown:

    python bench/bench_shield_attack.py --search [--worlds forest,gaps,warehouse] [--generations 3]
        [--population 8] [--max-steps 150] [--difficulty 0.9] [--workers 2]

The worlds are validation seeds (599,000 on by default), which no shield rule was tuned on.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

from companion.safety.shield import ShieldConfig
from training.attack_search import SearchConfig, search_attack
from training.attackers import ATTACKERS
from training.config import load_train_config
from training.episodes import NAV_ENV_ID, goal_worlds
from training.evaluate import evaluate, make_executor

CONFIG = Path(__file__).resolve().parents[1] / "training" / "configs" / "nav.toml"
#: the figures' header: per controller and shield
HEADER = "controller             shield episodes collisions  promised  least m  worst episode"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=4, help="worlds per family")
    parser.add_argument("--first-seed", type=int, default=599_000)
    parser.add_argument("--max-steps", type=int, default=400, help="steps per episode (10 a second)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--policy", type=Path, default=None, help="also fly this policy")
    parser.add_argument(
        "--autopilot-response", default="random", choices=("random", "ardupilot", "px4"),
        help="the firmware response flown, and so the envelope the gate assumes",
    )  # fmt: skip
    chunked = parser.add_argument_group("chunked", "a long run in chunks that resumes (--out)")
    chunked.add_argument("--out", type=Path, default=None, help="append each chunk here (JSON lines)")
    chunked.add_argument("--chunk", type=int, default=2, help="seeds per family in each chunk")
    chunked.add_argument(
        "--episodes", type=int, default=0, help="fly chunks until the file holds this many behind the gate"
    )
    search = parser.add_argument_group("search", "the search-based attacker (--search)")
    search.add_argument("--search", action="store_true", help="fly the search-based attacker instead")
    search.add_argument("--worlds", default="forest,gaps,warehouse", help="families, one world each")
    search.add_argument("--difficulty", type=float, default=0.9, help="the worlds' difficulty")
    search.add_argument("--generations", type=int, default=3)
    search.add_argument("--population", type=int, default=8, help="candidates (episodes) per generation")
    args = parser.parse_args()
    if args.search:
        search_bench(args)
        return
    if args.out is not None:
        chunked_bench(args)
        return
    config = load_train_config(CONFIG, overrides(args))
    env_config = config.env_config()
    worlds = goal_worlds(env_config.families, args.first_seed, args.seeds, env_config.difficulty_range)
    print(HEADER)
    for gate in (False, True):
        start = time.perf_counter()
        print_table(fly(args, config, worlds, gate), gate)
        print(f"  ({time.perf_counter() - start:.0f} s wall)")


def overrides(args: argparse.Namespace) -> list[str]:
    """The ``[env]`` keys the flags set: the episode length and the firmware response."""
    return [f"env.max_steps={args.max_steps}", f'env.autopilot_response="{args.autopilot_response}"']


def fly(args: argparse.Namespace, config, worlds, gate: bool) -> list[dict]:
    """Every attacker (and ``--policy``) over ``worlds`` behind the rules or the gate, one row per episode."""
    _, results = evaluate(
        args.policy, worlds, 1, config.env, args.workers, baselines=list(ATTACKERS), shield=True,
        env_id=NAV_ENV_ID, shield_config=ShieldConfig(backup_gate=gate),
    )  # fmt: skip
    return [
        {"controller": r.controller, "gate": gate, "world": r.world, "collision": bool(r.collision),
         "min_clearance": float(r.min_clearance), "steps": r.steps, "velocity_error": r.max_velocity_error,
         "best_effort": sum(n for k, n in r.shield_counts.items() if k.endswith("best_effort")),
         "response": r.response.get("name", "?") if r.response else "ideal"}
        for r in results
    ]  # fmt: skip


def print_table(rows: list[dict], gate: bool) -> None:
    """Per controller behind one shield: episodes, collisions (all, and those the gate's promise
    covers), the least clearance and its episode."""
    for name in sorted({r["controller"] for r in rows if r["gate"] == gate}):
        mine = [r for r in rows if r["controller"] == name and r["gate"] == gate]
        worst = min(mine, key=lambda r: r["min_clearance"])
        kept = [r for r in mine if not r["best_effort"]]
        promised = f"{sum(r['collision'] for r in kept)}/{len(kept)}" if gate else "-"
        collisions = sum(r["collision"] for r in mine)
        print(
            f"{name:22} {'gate' if gate else 'rules':6} {len(mine):8d} {collisions:10d} "
            f"{promised:>9} {worst['min_clearance']:8.3f}  {worst['world']} "
            f"({worst['response']}, step {worst['steps']}, velocity error up to "
            f"{worst['velocity_error']:.2f} m/s, {worst['best_effort']} best-effort steps)"
        )


def chunked_bench(args: argparse.Namespace) -> None:
    """Fly the seeds in chunks, each appended to ``--out`` once both shields have flown it; skip the
    chunks the file holds; then print the figures of every episode in it."""
    config = load_train_config(CONFIG, overrides(args))
    env_config = config.env_config()
    done: dict[int, list[dict]] = {}
    if args.out.is_file():
        for number, line in enumerate(args.out.read_text().splitlines(), 1):
            try:
                chunk = json.loads(line)
                done[int(chunk["first_seed"])] = chunk["episodes"]
                steps, seeds = int(chunk["max_steps"]), int(chunk["seeds"])
                response = str(chunk.get("response", "random"))
            except (ValueError, KeyError, TypeError, AttributeError) as error:
                raise SystemExit(f"bench_shield_attack: {args.out}:{number}: not a chunk ({error})") from None
            if (steps, seeds, response) != (args.max_steps, args.chunk, args.autopilot_response):
                raise SystemExit(
                    f"bench_shield_attack: {args.out}:{number}: a chunk of {seeds} seeds at {steps} steps "
                    f"({response}); this run flies {args.chunk} at {args.max_steps} "
                    f"({args.autopilot_response}) (a new file, or the same flags)"
                )
    per_chunk = len(env_config.families) * args.chunk * (len(ATTACKERS) + (args.policy is not None))
    chunks = math.ceil(args.episodes / per_chunk) if args.episodes else math.ceil(args.seeds / args.chunk)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    for k in range(chunks):
        first = args.first_seed + k * args.chunk
        if first in done:
            continue
        start = time.perf_counter()
        worlds = goal_worlds(env_config.families, first, args.chunk, env_config.difficulty_range)
        rows = [row for gate in (False, True) for row in fly(args, config, worlds, gate)]
        with args.out.open("a") as out:
            out.write(json.dumps({"first_seed": first, "seeds": args.chunk, "max_steps": args.max_steps,
                                  "response": args.autopilot_response, "episodes": rows}) + "\n")  # fmt: skip
        done[first] = rows
        wall = time.perf_counter() - start
        print(f"chunk from seed {first}: {len(rows)} episodes, {wall:.0f} s wall", flush=True)
    rows = [row for chunk in done.values() for row in chunk]
    print(f"{args.out}: {len(done)} chunks, {sum(r['gate'] for r in rows)} episodes behind the gate")
    print(HEADER)
    for gate in (False, True):
        print_table(rows, gate)


def search_bench(args: argparse.Namespace) -> None:
    """The search-based attacker behind the rules and behind the gate, world by world."""
    config = load_train_config(CONFIG, [f"env.max_steps={args.max_steps}"])
    families = [f.strip() for f in args.worlds.split(",") if f.strip()]
    worlds = goal_worlds(families, args.first_seed, 1, (args.difficulty, args.difficulty))
    budget = SearchConfig(generations=args.generations, population=args.population)
    print(f"search: {budget.generations} generations x {budget.population}, {args.max_steps} steps each")
    print(f"{'world':22} {'shield':6} {'least m':>8} {'collided':>8} {'per generation (least m)'}")
    total, start = 0, time.perf_counter()
    with make_executor(args.workers) as executor:
        for world in worlds:
            for gate in (False, True):
                found = search_attack(
                    world, config.env, True, ShieldConfig(backup_gate=gate), budget, executor, NAV_ENV_ID
                )
                total += found.episodes
                history = " ".join(f"{h:.3f}" for h in found.history)
                print(
                    f"{world.name:22} {'gate' if gate else 'rules':6} {found.min_clearance:8.3f} "
                    f"{'yes' if found.collision else 'no':>8} {history}"
                )
    print(f"  ({total} episodes, {time.perf_counter() - start:.0f} s wall)")


if __name__ == "__main__":
    main()
