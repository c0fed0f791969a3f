"""The companion on a workstation: the example config runs from the repository root with only
``autopilot.connect`` changed, command-line paths resolve from the working directory, recordings go
somewhere the user may write, and while no autopilot answers it says so every 5 s with the address."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from companion.config import default_recording_directory, load_config
from tests.companion.mavlink_peer import free_udp_port
from tests.onnx_models import write_policy

REPO = Path(__file__).resolve().parents[2]
EXAMPLE = REPO / "config" / "companion.example.toml"


def test_paths_in_the_file_resolve_from_the_file_and_on_the_command_line_from_the_working_directory(
    tmp_path, monkeypatch
):
    deploy = tmp_path / "deploy"
    write_policy(deploy / "policy.onnx")
    write_policy(tmp_path / "work" / "models" / "other.onnx")
    config = deploy / "companion.toml"
    config.write_text('[policy]\nmodel = "policy.onnx"\n[recorder]\ndirectory = "flights"\n')
    monkeypatch.chdir(tmp_path / "work")
    loaded = load_config(config)
    assert loaded.policy.model == str(deploy / "policy.onnx")
    assert loaded.recorder.directory == str(deploy / "flights")
    loaded = load_config(Path("../deploy/companion.toml"), ["policy.model=models/other.onnx",
                                                             'recorder.directory="runs"'])  # fmt: skip
    assert loaded.policy.model == str(tmp_path / "work" / "models" / "other.onnx")
    assert loaded.recorder.directory == str(tmp_path / "work" / "runs")
    absolute = tmp_path / "elsewhere.onnx"
    assert load_config(config, [f"policy.model={absolute}"]).policy.model == str(absolute)


def test_recordings_go_to_the_services_logs_directory_else_the_users_state_directory(tmp_path):
    service = default_recording_directory({"LOGS_DIRECTORY": "/var/log/lidar-avoid"})
    assert service == Path("/var/log/lidar-avoid/flights")
    user = default_recording_directory({"XDG_STATE_HOME": str(tmp_path)})
    assert user == tmp_path / "lidar-avoid" / "flights"
    home = Path.home() / ".local" / "state" / "lidar-avoid" / "flights"
    assert default_recording_directory({}) == home
    assert default_recording_directory({"XDG_STATE_HOME": "relative"}) == home  # the spec: ignored


def test_the_example_config_records_to_the_default_and_the_service_to_its_logs_directory(monkeypatch):
    """The example is also the service's config (systemd/install.sh copies it): systemd's
    ``LogsDirectory=lidar-avoid`` hands the service /var/log/lidar-avoid, where it records."""
    monkeypatch.delenv("LOGS_DIRECTORY", raising=False)
    unit = (REPO / "systemd" / "lidar-avoid-companion.service").read_text()
    assert "\nLogsDirectory=lidar-avoid\n" in unit
    config = load_config(EXAMPLE)
    assert config.recorder.enabled and not config.recorder.directory.startswith("/var/log")
    assert Path(config.policy.model).resolve() == (REPO / "models" / "policy.onnx").resolve()


def test_the_example_config_runs_from_the_repository_root_and_says_it_waits(tmp_path):
    """Before, it stopped at start-up (config/policy.onnx: file not found), recorded under
    /var/log/lidar-avoid, and said nothing after its first line while no autopilot answered."""
    address = f"udpin:127.0.0.1:{free_udp_port()}"
    env = {**os.environ, "XDG_STATE_HOME": str(tmp_path), "PYTHONPATH": str(REPO)}
    env.pop("LOGS_DIRECTORY", None)
    proc = subprocess.Popen(
        [sys.executable, "-m", "companion", "run", "--config", "config/companion.example.toml",
         f"autopilot.connect={address}", "params_check.timeout=2"],  # not 30 s of no heartbeat
        cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )  # fmt: skip
    lines: list[str] = []
    deadline = time.monotonic() + 60.0
    try:
        assert proc.stdout is not None
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if sum("waiting for the autopilot" in seen for seen in lines) == 2:
                break
        waiting = [line for line in lines if "waiting for the autopilot" in line]
        assert len(waiting) == 2, "".join(lines)
        assert f"waiting for the autopilot (ardupilot) on {address}: no heartbeat yet" in waiting[0]
        stamps = [time.strptime(line[:19], "%Y-%m-%d %H:%M:%S") for line in waiting]
        assert 4 <= time.mktime(stamps[1]) - time.mktime(stamps[0]) <= 6
    finally:
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0, "".join(lines) + out
    assert list((tmp_path / "lidar-avoid" / "flights").glob("flight-*.mcap"))
