"""``avoid-train evaluate --executor ray``: the same report as the local process pool, from Ray tasks on
a real local Ray; and one-line errors for a missing extra and an unreachable cluster."""

from __future__ import annotations

import json
import socket
import sys

import pytest

from training.__main__ import main

# two families, two controllers, two episodes: eight episodes whose order the report must keep
CONFIG = (
    'env_id = "flightsim/LidarNav-v0"\n[eval]\nfirst_seed = 500000\n'
    '[env]\nfamilies = ["gaps", "pillars"]\ndifficulty_range = [0.0, 0.3]\n'
)


@pytest.fixture
def config(tmp_path):
    path = tmp_path / "nav.toml"
    path.write_text(CONFIG)
    return path


def _evaluate(config, *extra: str) -> list[str]:
    return ["evaluate", "--config", str(config), "--seeds", "1", "--episodes", "2", "--shield", *extra]


@pytest.mark.timeout(240)
def test_ray_tasks_give_the_local_pools_report_in_the_same_order(config, tmp_path, capsys):
    import ray  # the [ray] extra is part of [test]: this runs in CI
    local, on_ray = tmp_path / "local.json", tmp_path / "ray.json"
    assert main([*_evaluate(config, "--workers", "2"), "--json", str(local)]) == 0
    assert main([*_evaluate(config, "--workers", "2", "--executor", "ray"), "--json", str(on_ray)]) == 0
    assert not ray.is_initialized()  # the local Ray it started is shut down again
    assert on_ray.read_text() == local.read_text()
    episodes = json.loads(on_ray.read_text())["episodes"]
    assert [(e["controller"], e["world"], e["episode"]) for e in episodes] == [
        (c, w, k)
        for c in ("goal_follower+shield", "straight_line+shield")
        for w in ("gaps-900000", "pillars-900000")
        for k in (0, 1)
    ]
    assert len({(e["steps"], e["distance"]) for e in episodes}) > 2  # real, different episodes


def test_without_ray_installed_the_error_names_the_extra(config, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # what `import ray` meets without the extra
    assert main(_evaluate(config, "--executor", "ray")) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--executor ray needs Ray" in err[0] and "pip install -e '.[ray]'" in err[0]


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


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
    address = address.format(port=_closed_port())
    assert main(_evaluate(config, "--executor", "ray", "--address", address)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--address {address}" in err[0] and message in err[0]


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
