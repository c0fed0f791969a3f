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

from companion.common.errors import UserError

log = logging.getLogger(__name__)

#: how long to wait for a TCP connection to ``--address``, and then for a gRPC handshake, before
#: calling it unreachable (Ray's own attempts take 30 s for ``ray://``, minutes for a GCS address)
CONNECT_TIMEOUT_S = 5.0

#: how many times to try a join that failed only because the head's Ray Client server for this
#: driver died as it started (:func:`server_died_at_start`): Ray's race, which met the first attempt
#: of 6 in 20 first joins to a fresh head here and 2 in 20 later ones (a retry is a later one), so
#: four in a row say something else is wrong. A failed attempt lasts ~40 s (Ray's client waits for
#: its log stream, which the head holds for its 30 s wait on the dead server)
JOIN_ATTEMPTS = 4

#: what Ray's client proxier answers when the server process it forked for a new Ray Client driver
#: died before serving (ray-project/ray#63202: the proxier forks it with gRPC threads running, and
#: the child can die before it runs a line, leaving empty logs): its check finds the child dead,
#: or a zombie on psutil's ``cmdline()``, or never answering; a new connection forks a new server
SERVER_START_FAILURES = (
    "Starting Ray client server failed",
    "psutil.ZombieProcess",
    "Proxy failed to Connect to backend",
)

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
        if address is None:  # "local": a new Ray even where `ray start` left a cluster to join
            ray.init("local", num_cpus=num_cpus, include_dashboard=False, logging_level=logging.ERROR)
            return
        if address != "auto":
            check_reachable(address)
        elif found := _auto_address(ray):  # a stale record would hang ray.init as a dead address does
            check_reachable(found, f"auto (found {found})")
        try:
            join(lambda: ray.init(address=address, logging_level=logging.ERROR), address)
        except ConnectionError as exc:
            hint = (
                f"the head's Ray Client could not start a server for this driver {JOIN_ATTEMPTS} times "
                "(its ray_client_server*.err logs say why)"
                if server_died_at_start(exc)
                else "a cluster with token authentication needs RAY_AUTH_MODE=token and its token here "
                "too: docs/training.md, On a Ray cluster"
            )
            message = f"--address {address}: cannot join the Ray cluster: {one_line(exc)} ({hint})"
            raise UserError(message) from None

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future:
        remote = self._remotes.get(fn)
        if remote is None:
            remote = self._remotes[fn] = self._ray.remote(fn)
        return remote.remote(*args, **kwargs).future()

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """Leave Ray: a local one stops, and a cluster drops the tasks this driver still owns."""
        self._ray.shutdown()


def server_died_at_start(exc: BaseException) -> bool:
    """Whether a failed ``ray.init("ray://...")`` is Ray's race at connect time (see
    :data:`SERVER_START_FAILURES`), which another attempt gets past, rather than an answer
    (authentication, versions, a dead head) that would only repeat."""
    text = str(exc)
    return (
        isinstance(exc, ConnectionAbortedError)
        and text.startswith("Initialization failure from server")
        and any(failure in text for failure in SERVER_START_FAILURES)
    )


def join(init: Callable[[], object], address: str, attempts: int = JOIN_ATTEMPTS) -> None:
    """Call ``init`` (a ``ray.init`` joining ``address``), again after each failure that
    :func:`server_died_at_start` calls Ray's race, at most ``attempts`` times in all, each retry
    logged in one line; any other failure, or the last, is raised at once. ``ray.init`` leaves no
    half-made client behind when it raises, so the next attempt starts clean."""
    for attempt in range(1, attempts + 1):
        try:
            init()
            return
        except ConnectionError as exc:
            if attempt == attempts or not server_died_at_start(exc):
                raise
            log.warning(
                "--address %s: the head's Ray Client server for this driver died as it started "
                "(Ray's fork race, ray-project/ray#63202: %s); joining again (%d of %d)",
                address, one_line(exc, last=True), attempt + 1, attempts,
            )  # fmt: skip


def one_line(exc: BaseException, last: bool = False) -> str:
    """An exception's message on one line: Ray's client puts the server's whole traceback after
    its first line, of which the last line (the exception) says what happened."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    if len(lines) < 2:
        return " ".join(lines)
    return lines[-1] if last else f"{lines[0]} {lines[-1]}"


def _auto_address(ray: Any) -> str | None:
    """The cluster Ray means by ``auto`` (``RAY_ADDRESS``, else the last ``ray start`` on this
    machine), or ``None`` when it finds none (``ray.init`` then says so at once)."""
    try:
        return ray._private.services.canonicalize_bootstrap_address("auto")
    except Exception:  # none found (ConnectionError), or a Ray without this helper: ray.init decides
        return None


def check_reachable(address: str, label: str | None = None) -> None:
    """Raise :class:`UserError` unless ``[ray://]HOST:PORT`` takes a TCP connection and completes a
    gRPC (HTTP/2) handshake, each within :data:`CONNECT_TIMEOUT_S`: Ray's own attempts on a dead or
    foreign address take from 30 s to minutes and may end the process instead of raising.
    ``label``: how the messages name the address (default: ``address``)."""
    label = label or address
    host, sep, port = address.removeprefix("ray://").rpartition(":")
    if not sep or not host or not port.isdigit():
        raise UserError(f"--address {label}: expected auto, HOST:PORT or ray://HOST:PORT")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=CONNECT_TIMEOUT_S):
            pass
    except OSError as exc:
        raise UserError(f"--address {label}: no Ray head reachable there ({exc})") from None
    try:
        import grpc  # Ray's transport; the [ray] extra's ray[client] brings its Python binding
    except ImportError:
        raise UserError(f"--address needs grpcio, part of the [ray] extra: {INSTALL_HINT}") from None
    with grpc.insecure_channel(f"{host}:{port}") as channel:
        try:
            grpc.channel_ready_future(channel).result(timeout=CONNECT_TIMEOUT_S)
        except grpc.FutureTimeoutError:
            raise UserError(
                f"--address {label}: something listens there but does not speak gRPC as a Ray head does"
            ) from None
