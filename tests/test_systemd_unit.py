"""The systemd unit's key settings, its check by systemd-analyze, and the install/uninstall scripts.

The unit is parsed as systemd reads it (sections, repeated keys kept in order). systemd-analyze
runs through ci/check-systemd.sh, the same script CI runs; those tests skip only where the
binary is absent. The install test stages into tmp_path with --root (real systemd-sysusers and
systemctl --root), never touching the machine.
"""

from __future__ import annotations

import re
import shlex
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
UNIT = REPO / "systemd" / "lidar-avoid-companion.service"
INSTALL = REPO / "systemd" / "install.sh"
UNINSTALL = REPO / "systemd" / "uninstall.sh"
CHECK = REPO / "ci" / "check-systemd.sh"


def parse_unit(text: str) -> dict[str, list[tuple[str, str]]]:
    """Sections -> [(key, value)] in file order; comments and blank lines dropped."""
    sections: dict[str, list[tuple[str, str]]] = {}
    current = None
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("[") and line.endswith("]"):
            current = sections.setdefault(line[1:-1], [])
            continue
        assert current is not None, f"setting outside a section: {line}"
        key, _, value = line.partition("=")
        current.append((key.strip(), value.strip()))
    return sections


@pytest.fixture(scope="module")
def unit() -> dict[str, list[tuple[str, str]]]:
    return parse_unit(UNIT.read_text())


def values(unit, section: str, key: str) -> list[str]:
    return [v for k, v in unit[section] if k == key]


def one(unit, section: str, key: str) -> str:
    found = values(unit, section, key)
    assert len(found) == 1, f"[{section}] {key}: {found}"
    return found[0]


def seconds(text: str) -> float:
    units = {"": 1, "s": 1, "ms": 0.001, "min": 60}
    match = re.fullmatch(r"(\d+(?:\.\d+)?)(ms|s|min|)", text)
    assert match, text
    return float(match[1]) * units[match[2]]


def script_var(script: Path, name: str) -> str:
    match = re.search(rf"^{name}=(\S+)$", script.read_text(), re.MULTILINE)
    assert match, name
    return match[1]


def test_notify_watchdog_and_restart_policy(unit):
    assert one(unit, "Service", "Type") == "notify"
    assert one(unit, "Service", "NotifyAccess") == "main"
    assert 1 <= seconds(one(unit, "Service", "WatchdogSec")) <= 10
    assert one(unit, "Service", "Restart") == "on-failure"
    # the start limit lives in [Unit] (systemd ignores it in [Service] since v230)
    assert seconds(one(unit, "Unit", "StartLimitIntervalSec")) > 0
    assert 1 <= int(one(unit, "Unit", "StartLimitBurst")) <= 10


def test_dedicated_user_with_serial_and_gpu_groups(unit):
    assert one(unit, "Service", "User") == "lidar-avoid"
    groups = one(unit, "Service", "SupplementaryGroups").split()
    assert {"dialout", "video", "render"} <= set(groups)
    sysusers = (REPO / "systemd" / "lidar-avoid.sysusers").read_text()
    assert re.search(r"^u lidar-avoid ", sysusers, re.MULTILINE)
    for group in groups:  # every supplementary group is created by the install step if missing
        assert re.search(rf"^m lidar-avoid {group}$", sysusers, re.MULTILINE), group


def test_hardening(unit):
    expected = {
        "ProtectSystem": "strict",
        "ProtectHome": "yes",
        "PrivateTmp": "yes",
        "NoNewPrivileges": "yes",
        "DevicePolicy": "closed",
        "StateDirectory": "lidar-avoid",
    }
    for key, value in expected.items():
        assert one(unit, "Service", key) == value, key
    assert not values(unit, "Service", "PrivateDevices")  # would hide the serial port and the GPU
    assert one(unit, "Service", "CapabilityBoundingSet") == ""


def test_devices_serial_and_gpu_allowed(unit):
    allowed = dict(v.split() for v in values(unit, "Service", "DeviceAllow"))
    assert allowed["/dev/ttyTHS1"] == "rw"
    for group in ("char-ttyTHS", "char-ttyUSB", "char-nvhost-*", "/dev/nvmap", "char-nvidia*"):
        assert allowed[group] == "rw", group


def test_address_families_include_can(unit):
    families = set(one(unit, "Service", "RestrictAddressFamilies").split())
    assert families == {"AF_UNIX", "AF_INET", "AF_INET6", "AF_NETLINK", "AF_CAN"}


def test_realtime_scheduling_for_the_loop_only(unit):
    assert one(unit, "Service", "CPUSchedulingPolicy") == "fifo"
    assert 1 <= int(one(unit, "Service", "CPUSchedulingPriority")) < 50  # below kernel IRQ threads
    assert one(unit, "Service", "CPUSchedulingResetOnFork") == "yes"


def test_execstart_matches_the_install_script(unit):
    argv = shlex.split(one(unit, "Service", "ExecStart"))
    prefix, conf_dir = script_var(INSTALL, "PREFIX"), script_var(INSTALL, "CONF_DIR")
    assert argv == [f"{prefix}/venv/bin/avoid-companion", "run", "--config", f"{conf_dir}/companion.toml"]
    assert script_var(UNINSTALL, "PREFIX") == prefix
    assert one(unit, "Install", "WantedBy") == "multi-user.target"


needs_analyze = pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze absent")


@needs_analyze
def test_systemd_analyze_verify_clean_and_exposure_within_target():
    done = subprocess.run([str(CHECK)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "verify: clean" in done.stdout
    exposure = float(re.search(r"Overall exposure level for \S+: (\d+\.\d+)", done.stdout)[1])
    assert exposure <= 4.0


@needs_analyze
@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        ("WatchdogSec=3s", "WatchdogSecs=3s", "Unknown key 'WatchdogSecs'"),
        ("Type=notify", "Type=notifyy", "Failed to parse service type"),
    ],
)
def test_check_script_fails_on_a_broken_unit(tmp_path, old, new, message):
    broken = tmp_path / "lidar-avoid-companion.service"
    broken.write_text(UNIT.read_text().replace(old, new))
    done = subprocess.run([str(CHECK), str(broken)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 1
    assert message in done.stderr


@needs_analyze
def test_check_script_fails_on_a_weakly_hardened_unit(tmp_path):
    weak = tmp_path / "weak.service"
    keep = [
        line
        for line in UNIT.read_text().splitlines()
        if not re.match(r"(Protect|Private|SystemCall|RestrictAddress|Capability|IPAddress)", line)
    ]
    weak.write_text("\n".join(keep) + "\n")
    done = subprocess.run([str(CHECK), str(weak)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 1 and "exposure above 4.0" in done.stderr


# ---------------------------------------------------------------------------------- install step

needs_systemd_tools = pytest.mark.skipif(
    shutil.which("systemd-sysusers") is None or shutil.which("systemctl") is None,
    reason="systemd-sysusers/systemctl absent",
)


def run_script(script: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(script), *args], capture_output=True, text=True, timeout=60)


def test_dry_run_prints_the_plan_and_changes_nothing(tmp_path):
    root = tmp_path / "image"
    done = run_script(INSTALL, "--root", str(root), "--dry-run", "--model", str(UNIT))
    assert done.returncode == 0, done.stderr
    out = done.stdout
    assert f"+ systemd-sysusers --root={root} {root}/etc/sysusers.d/lidar-avoid.conf" in out
    assert f"+ python3 -m venv {root}/opt/lidar-avoid/venv" in out
    # the base install: the checkout itself, no extras, so no torch
    assert f"+ {root}/opt/lidar-avoid/venv/bin/pip install {REPO}\n" in out
    assert "torch is installed in the companion venv" in out  # the guard runs after the install
    # PX4's link (mavsdk, in the base install) is proven to load at install time
    assert f'+ {root}/opt/lidar-avoid/venv/bin/python -c import companion.autopilot.px4' in out
    assert f"+ install -m 0644 {UNIT} {root}/etc/lidar-avoid/policy.onnx" in out
    assert f"+ systemctl --root={root} enable lidar-avoid-companion.service" in out
    assert "(dry run: nothing was changed)" in out
    assert not root.exists()


@needs_systemd_tools
def test_install_into_root_then_uninstall(tmp_path):
    root = tmp_path / "image"
    root.mkdir()
    model = tmp_path / "policy.onnx"
    model.write_bytes(b"not really onnx")
    done = run_script(INSTALL, "--root", str(root), "--no-venv", "--model", str(model))
    assert done.returncode == 0, done.stdout + done.stderr

    passwd = (root / "etc/passwd").read_text()
    assert re.search(r"^lidar-avoid:x:\d+:\d+:[^:]*:/var/lib/lidar-avoid:", passwd, re.MULTILINE)
    group = (root / "etc/group").read_text()
    for name in ("dialout", "video", "render"):
        assert re.search(rf"^{name}:x:\d+:lidar-avoid$", group, re.MULTILINE), name
    unit_copy = root / "etc/systemd/system/lidar-avoid-companion.service"
    assert unit_copy.read_text() == UNIT.read_text()
    wants = root / "etc/systemd/system/multi-user.target.wants/lidar-avoid-companion.service"
    assert wants.is_symlink()
    conf = root / "etc/lidar-avoid"
    assert (conf / "companion.toml").read_text() == (REPO / "config/companion.example.toml").read_text()
    assert (conf / "policy.onnx").read_bytes() == b"not really onnx"
    assert (conf / "firmware_params/px4.params").read_text() == (
        REPO / "firmware_params/px4.params"
    ).read_text()
    assert not (root / "opt/lidar-avoid/venv").exists()

    # a second install keeps the operator's edited config
    (conf / "companion.toml").write_text("# edited on the drone\n")
    done = run_script(INSTALL, "--root", str(root), "--no-venv")
    assert done.returncode == 0 and "kept existing /etc/lidar-avoid/companion.toml" in done.stdout
    assert (conf / "companion.toml").read_text() == "# edited on the drone\n"
    assert passwd == (root / "etc/passwd").read_text()  # idempotent: no second user

    done = run_script(UNINSTALL, "--root", str(root))
    assert done.returncode == 0, done.stderr
    assert not unit_copy.exists() and not wants.exists()
    assert (conf / "companion.toml").exists()  # kept without --purge

    done = run_script(UNINSTALL, "--root", str(root), "--purge")
    assert done.returncode == 0, done.stderr
    assert not conf.exists() and not (root / "etc/sysusers.d/lidar-avoid.conf").exists()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--frobnicate"], "unknown argument: --frobnicate"),
        (["--dry-run", "--model", "/no/such/model.onnx"], "--model /no/such/model.onnx: no such file"),
        (["--root"], "--root needs a directory"),
        (["--dry-run", "--root", "/tmp/x", "--now"], "--now cannot start a service installed with --root"),
    ],
)
def test_install_bad_arguments_exit_2_with_a_message(args, message):
    done = run_script(INSTALL, *args)
    assert done.returncode == 2
    assert message in done.stderr
