"""``avoid-train evaluate --executor ray``: the same report as the local process pool, from Ray tasks on
a real local Ray and on a real `ray start --head` cluster joined by address (GCS and Ray Client), all
on loopback; and one-line errors for a missing extra and an unreachable or foreign address."""

from __future__ import annotations

import json
import os
import secrets
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from tests.onnx_models import write_policy
from training.__main__ import main

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
    from companion.policy import PolicySpec
    from companion.scan import BIN_CONVENTION, N_BINS
    from training.config import load_train_config
    from training.evaluate import _layout

    path = tmp_path_factory.mktemp("ray-evaluation") / "nav.toml"
    path.write_text(CONFIG)
    train = load_train_config(path, [])
    env = train.env_config()
    spec = PolicySpec(
        stack=train.n_stack, n_bins=N_BINS, max_range=float(env.scan.max_range),
        bin_convention=BIN_CONVENTION, max_speed=float(env.max_speed), max_yaw_rate=float(env.max_yaw_rate),
        layout=_layout(env),
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


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def ray_head(tmp_path):
    """A real one-node Ray cluster on loopback, as `ray start --head` makes one, with token
    authentication: ``(gcs_port, client_port, env)``, ``env`` holding the token for the driver as
    the README says to give it to every machine."""
    gcs, client = _free_port(), _free_port()
    env = {**os.environ, "RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": secrets.token_hex(32)}
    # the head starts a server process per Ray Client connection and gives it 30 s to answer; under a
    # load average of 35 on this 2-core machine that failed once ("Initialization failure from server")
    env["RAY_CLIENT_SERVER_CHECK_CHANNEL_TIMEOUT_S"] = "180"
    log = tmp_path / "head.log"
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
    address = address.format(port=_free_port())
    assert main(_evaluate(config, "--executor", "ray", "--address", address)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--address {address}" in err[0] and message in err[0]


@pytest.mark.timeout(60)
def test_auto_finding_a_dead_cluster_is_one_line_and_exit_2(config, capsys, monkeypatch):
    monkeypatch.setenv("RAY_ADDRESS", f"127.0.0.1:{_free_port()}")  # as a stale `ray start` record
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
