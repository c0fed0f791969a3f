"""Evaluation episodes as Ray tasks, behind the ``concurrent.futures.Executor`` interface.

``avoid-train evaluate --executor ray`` hands this executor to the same ``run_tasks`` that the
local process pool feeds, so there is one evaluation path: each ``submit`` is a ``ray.remote``
task whose ``ObjectRef`` is returned as a ``concurrent.futures.Future``, and ``Executor.map``
yields the results in task order whichever machine finished first. Ray is the optional ``[ray]``
extra; it is imported only here.
"""

from __future__ import annotations

import logging
import socket
from collections.abc import Callable
from concurrent.futures import Executor, Future
from typing import Any

from companion.errors import UserError

#: how long to wait for a TCP connection to ``--address`` before calling it unreachable (Ray's own
#: connection attempts take 30 s for ``ray://`` and two minutes for a GCS address before giving up)
CONNECT_TIMEOUT_S = 5.0

INSTALL_HINT = "pip install -e '.[ray]' (or pip install 'ray[client]')"


class RayExecutor(Executor):
    """Submit callables as Ray tasks, one CPU each, on a local Ray or a cluster.

    :param address: ``None`` starts a local Ray of ``num_cpus`` CPUs, shut down with the executor;
        ``auto``, ``HOST:PORT`` (a head's GCS) or ``ray://HOST:PORT`` (Ray Client) joins a cluster
    :param num_cpus: the local Ray's CPUs (how many episodes run at once); only without ``address``
    """

    def __init__(self, address: str | None = None, num_cpus: int | None = None) -> None:
        try:
            import ray
        except ImportError:
            raise UserError(f"--executor ray needs Ray, the [ray] extra: {INSTALL_HINT}") from None
        self._ray = ray
        self._remotes: dict[Callable[..., Any], Any] = {}
        if address is None:
            ray.init(num_cpus=num_cpus, include_dashboard=False, logging_level=logging.ERROR)
            return
        if address != "auto":
            check_reachable(address)
        try:
            ray.init(address=address, logging_level=logging.ERROR)
        except ConnectionError as exc:
            raise UserError(f"--address {address}: cannot join the Ray cluster: {exc}") from None

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future:
        remote = self._remotes.get(fn)
        if remote is None:
            remote = self._remotes[fn] = self._ray.remote(fn)
        return remote.remote(*args, **kwargs).future()

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """Leave Ray: a local one stops, and a cluster drops the tasks this driver still owns."""
        self._ray.shutdown()


def check_reachable(address: str) -> None:
    """Raise :class:`UserError` unless ``[ray://]HOST:PORT`` takes a TCP connection within
    :data:`CONNECT_TIMEOUT_S` (an unreachable head fails in seconds, as one line)."""
    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if not sep or not host or not port.isdigit():
        raise UserError(f"--address {address}: expected auto, HOST:PORT or ray://HOST:PORT")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=CONNECT_TIMEOUT_S):
            pass
    except OSError as exc:
        raise UserError(f"--address {address}: no Ray head reachable there ({exc})") from None
