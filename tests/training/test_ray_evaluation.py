"""``avoid-train evaluate --executor ray``: the same report as the local process pool, from Ray tasks on
a real local Ray and on a real `ray start --head` cluster joined by address (GCS and Ray Client), all
on loopback; and one-line errors for a missing extra and an unreachable or foreign address."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

import pytest

from flightsim.sitl.companion_setup import free_tcp_port
from tests.onnx_models import write_policy
from tests.training.ray_head import ray_head as start_ray_head
from training.__main__ import main
from training.ray_executor import JOIN_ATTEMPTS, join, server_died_at_start

# two families; a policy file and two baselines: six episodes (at most 15 s each) whose order the
# report must keep
CONFIG = (
    'env_id = "flightsim/LidarNav-v0"\n[eval]\nfirst_seed = 500000\n'
    '[env]\nfamilies = ["gaps", "pillars"]\ndifficulty_range = [0.0, 0.3]\nmax_steps = 150\n'
)


@pytest.fixture(scope="module")
def config(tmp_path_factory):
    """The config, and beside it a small ONNX policy for its observation layout (``policy.onnx``),
    which every worker loads from its path."""
    from companion.guidance.policy import PolicySpec
    from companion.perception.scan import BIN_CONVENTION, N_BINS
    from training.config import load_train_config, observation_layout

    path = tmp_path_factory.mktemp("ray-evaluation") / "nav.toml"
    path.write_text(CONFIG)
    train = load_train_config(path, [])
    env = train.env_config()
    spec = PolicySpec(
        stack=train.n_stack, n_bins=N_BINS, max_range=float(env.scan.max_range),
        bin_convention=BIN_CONVENTION, max_speed=float(env.max_speed), max_yaw_rate=float(env.max_yaw_rate),
        layout=observation_layout(env),
    )  # fmt: skip
    write_policy(path.parent / "policy.onnx", kind="steer", spec=spec)  # actions follow the scan
    return path


def _evaluate(config, *extra: str) -> list[str]:
    policy = str(config.parent / "policy.onnx")
    return ["evaluate", "--config", str(config), "--policy", policy, "--seeds", "1", "--shield", *extra]


@pytest.fixture(scope="module")
def local_report(config) -> str:
    """The reference: the JSON report of the local process pool (two processes)."""
    out = config.parent / "local.json"
    assert main([*_evaluate(config, "--workers", "2"), "--json", str(out)]) == 0
    episodes = json.loads(out.read_text())["episodes"]
    assert [(e["controller"], e["world"]) for e in episodes] == [
        (c, w)
        for c in ("policy+shield", "goal_follower+shield", "straight_line+shield")
        for w in ("gaps-900000", "pillars-900000")
    ]
    assert len({(e["steps"], e["distance"]) for e in episodes}) > 2  # real, different episodes
    return out.read_text()


@pytest.mark.timeout(240)
def test_ray_tasks_on_a_local_ray_give_the_local_pools_report(config, local_report, tmp_path):
    import ray  # the [ray] extra is part of [test]: this runs in CI

    out = tmp_path / "ray.json"
    assert main([*_evaluate(config, "--workers", "2", "--executor", "ray"), "--json", str(out)]) == 0
    assert not ray.is_initialized()  # the local Ray it started is shut down again
    assert out.read_text() == local_report


@pytest.fixture
def ray_head(tmp_path):
    """A real one-node Ray cluster on loopback (:func:`tests.training.ray_head.ray_head`)."""
    with start_ray_head(tmp_path / "head.log") as head:
        yield head


@pytest.mark.timeout(240)
def test_a_cluster_joined_by_address_gives_the_local_pools_report(config, local_report, ray_head, tmp_path):
    gcs, client, env = ray_head
    for address in (f"127.0.0.1:{gcs}", f"ray://127.0.0.1:{client}"):
        out = tmp_path / "cluster.json"
        # a process of its own, as on a user's machine: Ray reads the token once per process
        argv = [sys.executable, "-m", "training"]
        argv += _evaluate(config, "--executor", "ray", "--address", address, "--json", str(out))
        done = subprocess.run(argv, env=env, capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
        assert out.read_text() == local_report, address


def test_without_ray_installed_the_error_names_the_extra(config, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # what `import ray` meets without the extra
    assert main(_evaluate(config, "--executor", "ray")) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--executor ray needs Ray" in err[0] and "pip install -e '.[ray]'" in err[0]


@pytest.mark.timeout(60)  # Ray itself would try a dead GCS address for two minutes
@pytest.mark.parametrize(
    ("address", "message"),
    [
        ("127.0.0.1:{port}", "no Ray head reachable there"),
        ("ray://127.0.0.1:{port}", "no Ray head reachable there"),
        ("nohost.invalid:6379", "no Ray head reachable there"),
        ("headnode", "expected auto, HOST:PORT or ray://HOST:PORT"),
    ],
)
def test_an_unreachable_address_is_one_line_and_exit_2(config, capsys, address, message):
    address = address.format(port=free_tcp_port())
    assert main(_evaluate(config, "--executor", "ray", "--address", address)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--address {address}" in err[0] and message in err[0]


@pytest.mark.timeout(60)
def test_auto_finding_a_dead_cluster_is_one_line_and_exit_2(config, capsys, monkeypatch):
    monkeypatch.setenv("RAY_ADDRESS", f"127.0.0.1:{free_tcp_port()}")  # as a stale `ray start` record
    assert main(_evaluate(config, "--executor", "ray", "--address", "auto")) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--address auto (found " in err[0] and "no Ray head reachable there" in err[0]


@pytest.mark.timeout(60)
def test_an_address_where_no_ray_head_answers_is_one_line_and_exit_2(config, capsys):
    with socket.socket() as listener:  # takes TCP connections (the kernel's backlog) but says nothing
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        address = "{}:{}".format(*listener.getsockname())
        assert main(_evaluate(config, "--executor", "ray", "--address", address)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "does not speak gRPC as a Ray head does" in err[0]


# What Ray's client raised when the head's Ray Client server for the driver died as it started (Ray's
# fork race, ray-project/ray#63202), as seen here: in CI (ZombieProcess), in the bench (the server found
# dead), and the proxier's answer when the server never answers; the tracebacks shortened
ZOMBIE = (
    "Initialization failure from server:\nTraceback (most recent call last):\n"
    '  File ".../ray/util/client/server/proxier.py", line 396, in start_specific_server\n'
    "    cmd = psutil_proc.cmdline()\n"
    "psutil.ZombieProcess: PID still exists but it's a zombie (pid=18047)\n"
)
DIED = (
    "Initialization failure from server:\nTraceback (most recent call last):\n"
    '  File ".../ray/util/client/server/proxier.py", line 771, in Datapath\n'
    "RuntimeError: Starting Ray client server failed. See ray_client_server_23000.err for detailed logs.\n"
)
SILENT = (
    "Initialization failure from server:\nTraceback ...\nRuntimeError: Proxy failed to Connect to backend!"
)


@pytest.mark.parametrize("message", [ZOMBIE, DIED, SILENT])
def test_a_server_that_died_at_start_is_rays_race(message):
    assert server_died_at_start(ConnectionAbortedError(message))


@pytest.mark.parametrize(
    "exc",
    [
        ConnectionAbortedError(
            "Initialization failure from server:\nray.exceptions.AuthenticationError: bad token"
        ),
        ConnectionError("ray client connection timeout"),  # the head itself does not answer
        ConnectionError(ZOMBIE),  # not what Ray's client raises for a failed start
        ConnectionAbortedError(ZOMBIE.removeprefix("Initialization failure from server:")),
        RuntimeError(DIED),
    ],
)
def test_any_other_failure_is_not(exc):
    assert not server_died_at_start(exc)


class _Init:
    """``ray.init`` as ``join`` calls it: raises ``failures`` one after another, then joins."""

    def __init__(self, *failures: BaseException) -> None:
        self.failures = list(failures)
        self.calls = 0

    def __call__(self) -> None:
        self.calls += 1
        if self.failures:
            raise self.failures.pop(0)


def test_join_tries_again_after_rays_race_each_time_in_one_line(caplog):
    init = _Init(ConnectionAbortedError(ZOMBIE), ConnectionAbortedError(DIED))
    join(init, "ray://head:10001", attempts=3)
    assert init.calls == 3
    retries = [r.getMessage() for r in caplog.records if r.name == "training.ray_executor"]
    assert len(retries) == 2 and all("\n" not in r and "ray://head:10001" in r for r in retries)
    assert "psutil.ZombieProcess: PID still exists" in retries[0] and "(2 of 3)" in retries[0]
    assert "Starting Ray client server failed" in retries[1] and "(3 of 3)" in retries[1]


def test_join_gives_up_after_its_attempts():
    init = _Init(*(ConnectionAbortedError(DIED) for _ in range(JOIN_ATTEMPTS + 1)))
    with pytest.raises(ConnectionAbortedError, match="Starting Ray client server failed"):
        join(init, "ray://head:10001")
    assert init.calls == JOIN_ATTEMPTS == 4


def test_join_raises_any_other_failure_at_once(caplog):
    init = _Init(ConnectionError("ray client connection timeout"))
    with pytest.raises(ConnectionError, match="timeout"):
        join(init, "ray://head:10001")
    assert init.calls == 1 and not caplog.records


@pytest.mark.timeout(60)
def test_a_join_that_keeps_meeting_rays_race_is_one_line_and_exit_2(config, capsys, monkeypatch):
    import grpc
    import ray

    init = _Init(*(ConnectionAbortedError(ZOMBIE) for _ in range(JOIN_ATTEMPTS)))
    monkeypatch.setattr(ray, "init", lambda *args, **kwargs: init())  # the race cannot be had on demand
    server = grpc.server(ThreadPoolExecutor(max_workers=1))  # a real gRPC head for check_reachable
    address = f"ray://127.0.0.1:{server.add_insecure_port('127.0.0.1:0')}"
    server.start()
    try:
        assert main(_evaluate(config, "--executor", "ray", "--address", address)) == 2
    finally:
        server.stop(None)
    err = [line for line in capsys.readouterr().err.strip().splitlines() if "error:" in line]
    assert init.calls == JOIN_ATTEMPTS
    assert len(err) == 1 and f"--address {address}: cannot join the Ray cluster: " in err[0]
    assert "psutil.ZombieProcess" in err[0] and f"a server for this driver {JOIN_ATTEMPTS} times" in err[0]


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--address", "auto"], "it needs --executor ray"),
        (["--executor", "ray", "--address", "auto", "--workers", "4"], "the cluster's CPUs decide"),
    ],
)
def test_address_only_with_ray_and_without_workers(config, capsys, extra, message):
    assert main(_evaluate(config, *extra)) == 2
    assert message in capsys.readouterr().err
