"""Joins by Ray Client (``ray://``) to a real `ray start --head` on loopback: how often Ray's first
attempt fails, and how often a join still fails after ``training.ray_executor.join``'s retries.

Usage::

    python bench/bench_ray_client_joins.py [--joins 40]

Starts a one-node head with token authentication (as the tests do), then joins it ``--joins``
times from this process through ``join`` (``ray.init("ray://...")``, then ``ray.shutdown()``).
Every attempt is recorded: the first attempt of each join is what a bare ``ray.init`` meets (the
reference: Ray's own failure rate, ray-project/ray#63202), the join's outcome is what
``avoid-train evaluate --address ray://...`` meets. Prints both counts, what each failure said, the
seconds a join and a failed attempt take, and the load average.
"""

from __future__ import annotations

import argparse
import logging
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.training.ray_head import ray_head
from training.ray_executor import JOIN_ATTEMPTS, _one_line, join


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
            self.record.append((time.perf_counter() - start, _one_line(exc, last=True)))
            raise
        self.record.append((time.perf_counter() - start, None))


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--joins", type=int, default=40)
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")

    with tempfile.TemporaryDirectory() as tmp, ray_head(Path(tmp) / "head.log") as (_, client, env):
        os.environ.update({k: env[k] for k in ("RAY_AUTH_MODE", "RAY_AUTH_TOKEN")})  # before Ray reads them
        import ray

        address = f"ray://127.0.0.1:{client}"
        joins: list[list[tuple[float, str | None]]] = []  # per join, per attempt
        join_s: list[float] = []
        for _ in range(args.joins):
            attempts = Attempts(ray, address)
            start = time.perf_counter()
            try:
                join(attempts, address)
                ray.shutdown()
            except ConnectionError:
                pass
            join_s.append(time.perf_counter() - start)
            joins.append(attempts.record)

    first_failed = [a[0][1] for a in joins if a[0][1] is not None]
    failed = [a for a in joins if a[-1][1] is not None]
    failed_s = [s for a in joins for s, failure in a if failure is not None]
    n = len(joins)
    print(f"joins by ray://: {n}; load average {os.getloadavg()[0]:.1f}")
    k = len(first_failed)
    print(f"  first attempt failed (a bare ray.init, the reference): {k} ({k / n:.0%})")
    print(f"  join failed after up to {JOIN_ATTEMPTS} attempts (join): {len(failed)} ({len(failed) / n:.0%})")
    print(f"  attempts in all: {sum(len(a) for a in joins)}")
    for failure in sorted(set(first_failed)):
        print(f"  failure: {failure} x {first_failed.count(failure)}")
    print(f"  seconds per join: median {statistics.median(join_s):.1f}, max {max(join_s):.1f}")
    if failed_s:
        median, worst = statistics.median(failed_s), max(failed_s)
        print(f"  seconds per failed attempt: median {median:.1f}, max {worst:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
