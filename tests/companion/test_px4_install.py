"""PX4 works from every install: mavsdk is in the base install, and a missing one is one line, exit 2."""

from __future__ import annotations

import subprocess
import sys

from companion.common.tomlconfig import tomllib
from tests.companion.companion_process import REPO, free_udp_port, write_config
from tests.onnx_models import write_policy

WITHOUT_MAVSDK = """
import importlib.abc, sys

class Missing(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] == "mavsdk":
            raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        return None

sys.meta_path.insert(0, Missing())
from companion.__main__ import main
sys.exit(main(["run", "--config", sys.argv[1]]))
"""


def test_mavsdk_is_in_the_base_install_so_sim_and_service_installs_have_it():
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    base = {d.split(">")[0].split("=")[0].split(";")[0].strip() for d in project["dependencies"]}
    assert "mavsdk" in base  # `pip install -e '.[sim]'` and systemd/install.sh (base install) get it
    (mavsdk,) = [d for d in project["dependencies"] if d.startswith("mavsdk")]
    assert mavsdk == "mavsdk>=4"  # the native binding's API companion/autopilot/px4.py uses


def test_px4_without_mavsdk_is_one_line_exit_2(tmp_path):
    model = write_policy(tmp_path / "m.onnx")
    config = write_config(tmp_path, model, free_udp_port(), free_udp_port(), autopilot="px4")
    script = tmp_path / "without_mavsdk.py"
    script.write_text(WITHOUT_MAVSDK)
    done = subprocess.run(
        [sys.executable, str(script), str(config)], cwd=REPO, capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 2, done.stderr
    assert "Traceback" not in done.stderr
    # the log lines of what was opened before it (policy, lidar), then the one error line
    errors = [line for line in done.stderr.splitlines() if " INFO " not in line and " WARNING " not in line]
    assert len(errors) == 1, done.stderr
    assert errors[0].startswith("avoid-companion: error: autopilot.type = px4 needs mavsdk >= 4")
