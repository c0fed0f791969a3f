"""Evaluation on the local process pool against Ray tasks: wall time of each, and the same report.

Usage::

    python bench/bench_eval_executors.py [--config training/configs/nav.toml] [--seeds 2] [--repeats 2]
        [--address ADDR]

Runs ``avoid-train evaluate --config CONFIG --seeds N --json …`` (the baselines; no policy) as a
subprocess, alternately with ``--executor local`` (the reference: one process per core) and
``--executor ray`` (a local Ray of one CPU per core, started and stopped by the command, or the
cluster at ``--address``), ``--repeats`` times each after one untimed local warm-up run (numba's
compile cache). Prints every wall time, the best of each executor and their ratio (Ray / local),
the load average, and whether every run's JSON report is byte-identical to the first local one.
On one machine the ratio can only show Ray's overhead (its start-up, a few seconds); what Ray adds
is more machines.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def run(config: Path, seeds: int, executor: str, address: str | None, out: Path) -> float:
    """Wall seconds of one ``avoid-train evaluate`` run, its report written to ``out``."""
    argv = [sys.executable, "-m", "training", "evaluate", "--config", str(config), "--seeds", str(seeds)]
    argv += ["--executor", executor, "--json", str(out)]
    if address and executor == "ray":
        argv += ["--address", address]
    start = time.perf_counter()
    subprocess.run(argv, cwd=REPO, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - start


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--config", type=Path, default=REPO / "training/configs/nav.toml")
    parser.add_argument("--seeds", type=int, default=2, help="test worlds per family")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--address", help="a Ray cluster to run the Ray side on (default: a local Ray)")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        reference = Path(tmp) / "reference.json"
        run(args.config, args.seeds, "local", None, reference)  # warm-up: compiles numba's cache
        times: dict[str, list[float]] = {"local": [], "ray": []}
        same = True
        for i in range(args.repeats):
            for executor in ("local", "ray"):
                out = Path(tmp) / f"{executor}-{i}.json"
                times[executor].append(run(args.config, args.seeds, executor, args.address, out))
                same = same and out.read_bytes() == reference.read_bytes()
                print(f"  {executor:<5} run {i + 1}: {times[executor][-1]:6.1f} s", flush=True)
    local, ray = min(times["local"]), min(times["ray"])
    where = args.address or f"a local Ray of {os.cpu_count()} CPUs"
    print(f"evaluate --config {args.config.name} --seeds {args.seeds} (baselines), {os.cpu_count()} cores, "
          f"load average {os.getloadavg()[0]:.1f}")
    print(f"local process pool: {local:6.1f} s (best of {args.repeats})")
    print(f"Ray tasks ({where}): {ray:6.1f} s (best of {args.repeats})")
    print(f"ratio Ray / local: {ray / local:.2f}")
    print(f"reports byte-identical to the local reference: {'yes' if same else 'NO'}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
