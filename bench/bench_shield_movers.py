"""Figures: attackers in worlds with movers, behind the gate as it was (``none``: movers unseen, their
returns remembered as standing ones) and behind the gate that sees them move, on the same episodes:
the movers and their scan bins from the simulator's truth (``truth``), or from the env's scan tracker
as the companion tracks them in flight (``tracker``).

LidarNav-v0 runs unshielded and :func:`training.mover_attack.fly` applies the shield in the loop;
one firmware response for all
(``--autopilot``), so the gate's envelope is the one flown. Prints per attacker and gate: episodes,
contacts with a mover while the vehicle moved faster than the creep and at rest, the least gap to a
mover while moving and to the static world (m, from the vehicle's surface), and the counts of
``mover_too_fast``, ``gate_mover_best_effort`` and ``gate_give_way`` (``--no-give-way``: the gate
without ``[shield] give_way``). The dynamic families' walkers keep within the
default 1.5 m/s; forklifts (up to 2 m/s) and drones (up to 3 m/s) may not, and are counted.

    python bench/bench_shield_movers.py [--families office-dynamic,rooms-dynamic] [--seeds 8]
        [--first-seed 500100] [--max-steps 200] [--autopilot ardupilot] [--mover-accel 3.0] [--no-give-way]

The worlds are validation seeds (500,100 on by default).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from companion.safety.shield import ShieldConfig
from training.config import load_train_config
from training.episodes import NAV_ENV_ID, goal_worlds, make_eval_env
from training.mover_attack import MOVER_ATTACKERS, fly

CONFIG = Path(__file__).resolve().parents[1] / "training" / "configs" / "nav.toml"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--families", default="office-dynamic,rooms-dynamic", help="dynamic families")
    parser.add_argument("--seeds", type=int, default=8, help="worlds per family")
    parser.add_argument("--first-seed", type=int, default=500_100)
    parser.add_argument("--max-steps", type=int, default=200, help="steps per episode (10 a second)")
    parser.add_argument("--autopilot", default="ardupilot", choices=("ardupilot", "px4", "random", "ideal"))
    parser.add_argument("--mover-accel", type=float, default=ShieldConfig.mover_accel, help="m/s²")
    parser.add_argument("--no-give-way", action="store_true", help="the gate without [shield] give_way")
    args = parser.parse_args()
    families = [f.strip() for f in args.families.split(",") if f.strip()]
    overrides = [
        f"env.max_steps={args.max_steps}",
        f"env.families={json.dumps(families)}",
        f"env.autopilot_response={json.dumps(args.autopilot)}",
    ]
    env = make_eval_env(load_train_config(CONFIG, overrides).env, NAV_ENV_ID)
    worlds = goal_worlds(families, args.first_seed, args.seeds, (0.9, 0.9))
    config = ShieldConfig(backup_gate=True, mover_accel=args.mover_accel, give_way=not args.no_give_way)
    header = (
        "attacker",
        "gate",
        "episodes",
        "moving",
        "at rest",
        "least mover",
        "least static",
        "too fast",
        "best effort",
        "gave way",
    )
    print(f"{header[0]:10} {header[1]:7} " + " ".join(f"{h:>12}" for h in header[2:]))
    for attacker in MOVER_ATTACKERS:
        for movers in ("none", "truth", "tracker"):
            start = time.perf_counter()
            flights = [fly(env, world, attacker, movers, config) for world in worlds]
            moving = sum(len(f.while_moving) for f in flights)
            at_rest = sum(len(f.contacts) for f in flights) - moving
            counts = [
                sum(f.interventions[k] for f in flights)
                for k in ("mover_too_fast", "gate_mover_best_effort", "gate_give_way")
            ]
            print(
                f"{attacker:10} {movers:7} "
                f"{len(flights):12d} {moving:12d} {at_rest:12d} "
                f"{min(f.moving_gap for f in flights):12.2f} {min(f.static_gap for f in flights):12.2f} "
                f"{counts[0]:12d} {counts[1]:12d} {counts[2]:12d}  ({time.perf_counter() - start:.0f} s)",
                flush=True,
            )
    env.close()


if __name__ == "__main__":
    main()
