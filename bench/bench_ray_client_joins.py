"""Joins by Ray Client (``ray://``) to a real `ray start --head` on loopback: how often Ray's first
attempt fails, and how often a join still fails after ``training.ray_executor.join``'s retries.

Usage::

    python bench/bench_ray_client_joins.py [--heads 1] [--joins 40]

Starts ``--heads`` one-node heads one after another, with token authentication (as the tests do),
and joins each ``--joins`` times from this process through ``join`` (``ray.init("ray://...")``,
then ``ray.shutdown()``); a head's first join is counted apart (the tests make one per head).
Every attempt is recorded: the first attempt of each join is what a bare ``ray.init`` meets (the
reference: Ray's own failure rate, ray-project/ray#63202), the join's outcome is what
``avoid-train evaluate --address ray://...`` meets. Prints both counts, what each failure said, the
seconds a join and a failed attempt take, and the load average.
"""

from __future__ import annotations

import argparse
import logging
import os
import secrets
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.training.ray_head import ray_head
from training.ray_executor import JOIN_ATTEMPTS, join, one_line


class Attempts:
    """``ray.init`` joining ``address``, each call recorded: (seconds, its failure on one line or None)."""

    def __init__(self, ray, address: str) -> None:
        self.ray, self.address = ray, address
        self.record: list[tuple[float, str | None]] = []

    def __call__(self) -> None:
        start = time.perf_counter()
        try:
            self.ray.init(address=self.address, logging_level=logging.ERROR)
        except ConnectionError as exc:
            self.record.append((time.perf_counter() - start, one_line(exc, last=True)))
            raise
        self.record.append((time.perf_counter() - start, None))


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--heads", type=int, default=1, help="heads started one after another")
    parser.add_argument("--joins", type=int, default=40, help="joins to each head")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    token = secrets.token_hex(32)  # one for every head: Ray reads it once per process
    os.environ.update({"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": token})
    import ray

    joins: list[list[tuple[float, str | None]]] = []  # per join, per attempt
    first_of_head: list[bool] = []
    join_s: list[float] = []
    with tempfile.TemporaryDirectory() as tmp:
        for h in range(args.heads):
            with ray_head(Path(tmp) / f"head-{h}.log", token) as (_, client, _):
                address = f"ray://127.0.0.1:{client}"
                for j in range(args.joins):
                    attempts = Attempts(ray, address)
                    start = time.perf_counter()
                    try:
                        join(attempts, address)
                        ray.shutdown()
                    except ConnectionError:
                        pass
                    join_s.append(time.perf_counter() - start)
                    joins.append(attempts.record)
                    first_of_head.append(j == 0)

    n = len(joins)
    print(f"joins by ray://: {n} ({args.heads} heads x {args.joins}); load average {os.getloadavg()[0]:.1f}")
    for label, which in (("a head's first join", True), ("its later joins", False)):
        mine = [a for a, first in zip(joins, first_of_head, strict=True) if first == which]
        if mine:
            k = sum(a[0][1] is not None for a in mine)
            print(f"  {label}: first attempt failed (a bare ray.init, the reference): {k} of {len(mine)}")
    failed = [a for a in joins if a[-1][1] is not None]
    print(f"  joins failed after up to {JOIN_ATTEMPTS} attempts (join): {len(failed)} of {n}")
    print(f"  attempts in all: {sum(len(a) for a in joins)}")
    first_failed = [a[0][1] for a in joins if a[0][1] is not None]
    for failure in sorted(set(first_failed)):
        print(f"  failure: {failure} x {first_failed.count(failure)}")
    print(f"  seconds per join: median {statistics.median(join_s):.1f}, max {max(join_s):.1f}")
    failed_s = [s for a in joins for s, failure in a if failure is not None]
    if failed_s:
        median, worst = statistics.median(failed_s), max(failed_s)
        print(f"  seconds per failed attempt: median {median:.1f}, max {worst:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
