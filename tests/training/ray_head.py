"""A real one-node Ray cluster on loopback, as `ray start --head` makes one, for the Ray tests and
``bench/bench_ray_client_joins.py``."""

from __future__ import annotations

import os
import secrets
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from flightsim.sitl.companion_setup import free_tcp_port

#: the ports `ray start --head` takes for itself by default (GCS 6379, dashboard 8265, Ray Client
#: 10001, workers 10002-19999); it refuses a chosen port among them ("used by other components")
RAY_DEFAULT_PORTS = frozenset({6379, 8265, *range(10001, 20000)})


@contextmanager
def ray_head(log: Path, token: str | None = None) -> Iterator[tuple[int, int, dict[str, str]]]:
    """`ray start --head --block` with token authentication (``token``, default a new one), its
    output in ``log``, stopped (all its processes) on leaving: ``(gcs_port, client_port, env)``,
    ``env`` holding the token for the driver as the README says to give it to every machine."""
    gcs, client = free_tcp_port(RAY_DEFAULT_PORTS), free_tcp_port(RAY_DEFAULT_PORTS)
    # Ray's defaults otherwise: its Ray Client server per driver answers within 1-3 s here, well
    # inside the 30 s Ray gives it; when one dies at birth instead (ray-project/ray#63202), the
    # driver's failed attempt lasts about that long, so a longer wait would only slow the retry
    env = {**os.environ, "RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": token or secrets.token_hex(32)}
    argv = [sys.executable, "-m", "ray.scripts.scripts", "start", "--head", "--block", "--node-ip-address",
            "127.0.0.1", "--port", str(gcs), "--ray-client-server-port", str(client), "--num-cpus", "2",
            "--include-dashboard=false", "--disable-usage-stats"]  # fmt: skip
    with log.open("w") as sink:
        head = subprocess.Popen(argv, env=env, stdout=sink, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline = time.monotonic() + 90
        while "Ray runtime started" not in log.read_text():
            assert head.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.2)
        yield gcs, client, env
    finally:
        head.terminate()  # --block: `ray start` stops the cluster's processes on SIGTERM
        head.wait(timeout=60)
        record = Path(tempfile.gettempdir(), "ray", "ray_current_cluster")  # what `auto` would join
        if record.is_file() and record.read_text().strip().endswith(f":{gcs}"):
            record.unlink()
