"""The companion imports and flies with the training stack made unimportable.

ARCHITECTURE.md: ``companion`` depends on numpy, onnxruntime, pymavlink, python-can (mavsdk for
PX4) only. A meta-path hook, installed before anything else runs, refuses torch, jsbsim,
gymnasium, stable_baselines3 and the project's flightsim/training packages, and records every
attempt; the companion must neither need nor even try them.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

from tests.companion.companion_process import REPO, LidarSender, free_udp_port, stop, write_config
from tests.companion.mavlink_peer import SimulatedAutopilot
from tests.onnx_models import write_policy

FORBIDDEN = ("torch", "jsbsim", "gymnasium", "stable_baselines3", "flightsim", "training", "onnx")

BLOCKER = '''
import atexit, importlib.abc, sys
FORBIDDEN = {forbidden!r}
attempts = []

class Blocker(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in FORBIDDEN:
            attempts.append(name)
            raise ImportError(f"{{name}} is blocked: the companion must not need it")
        return None

sys.meta_path.insert(0, Blocker())

@atexit.register
def report():
    loaded = sorted(m for m in sys.modules if m.split(".")[0] in FORBIDDEN)
    sys.stderr.write(f"ISOLATION attempts={{sorted(set(attempts))}} loaded={{loaded}}\\n")
'''

COMPANION_MODULES = (
    "companion.app",
    "companion.config",
    "companion.guidance.policy",
    "companion.safety.shield",
    "companion.safety.supervisor",
    "companion.notify",
    "companion.params.check",
    "companion.params.client",
    "companion.params.files",
    "companion.autopilot.obstacle_distance",
    "companion.autopilot.ardupilot",
    "companion.autopilot.px4",
    "companion.lidar.velodyne",
    "companion.lidar.vlp16_packet",
)


def _bootstrap(tmp_path: Path, then: str) -> Path:
    script = tmp_path / "isolated.py"
    script.write_text(BLOCKER.format(forbidden=FORBIDDEN) + then)
    return script


def test_the_blocker_blocks(tmp_path):
    script = _bootstrap(tmp_path, "import torch\n")
    result = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, cwd=REPO)
    assert result.returncode != 0 and "torch is blocked" in result.stderr


def test_every_companion_module_imports(tmp_path):
    lines = [f"import {m}" for m in COMPANION_MODULES]
    can_ring = REPO / "companion" / "lidar" / "can_ring.py"
    if can_ring.exists():
        lines.append("import companion.lidar.can_ring")
    script = _bootstrap(tmp_path, "\n".join(lines) + "\n")
    result = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, cwd=REPO,
                            timeout=120)
    assert result.returncode == 0, result.stderr
    assert "ISOLATION attempts=[] loaded=[]" in result.stderr


def test_companion_flies_without_the_training_stack(tmp_path):
    lidar_port, mavlink_port = free_udp_port(), free_udp_port()
    model = write_policy(tmp_path / "forward.onnx", kind="forward")  # built here, with onnx
    config = write_config(tmp_path, model, lidar_port, mavlink_port)
    script = _bootstrap(
        tmp_path,
        "import runpy\n"
        f"sys.argv = ['avoid-companion', 'run', '--config', {str(config)!r}]\n"
        "runpy.run_module('companion', run_name='__main__')\n",
    )
    vehicle = SimulatedAutopilot(f"udpout:127.0.0.1:{mavlink_port}")
    proc = subprocess.Popen([sys.executable, str(script)], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    lidar = LidarSender(lidar_port)
    try:
        lidar.on = True
        deadline = time.monotonic() + 20
        while not vehicle.messages("SET_POSITION_TARGET_LOCAL_NED") and time.monotonic() < deadline:
            assert proc.poll() is None, proc.communicate()[1]
            time.sleep(0.05)
        setpoints = vehicle.messages("SET_POSITION_TARGET_LOCAL_NED")
        assert setpoints, "no setpoint from the isolated companion"
    finally:
        lidar.close()
        code, _out, err = stop(proc)
        vehicle.close()
    assert code == 0, err
    assert "ISOLATION attempts=[] loaded=[]" in err, err[-2000:]
