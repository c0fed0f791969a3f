"""The companion config: the documented example loads, every key is documented, mistakes name the key."""

from __future__ import annotations

import dataclasses
import re
import typing
from pathlib import Path

import pytest

from companion.common.errors import UserError
from companion.common.tomlconfig import load_toml
from companion.config import CompanionConfig, load_config

EXAMPLE = Path(__file__).resolve().parents[2] / "config" / "companion.example.toml"


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "companion.toml"
    path.write_text('[policy]\nmodel = "policy.onnx"\n' + text)
    return path


def test_example_config_loads():
    config = load_config(EXAMPLE)
    assert config.lidar.source == "velodyne"
    assert config.lidar.velodyne.port == 2368
    assert [s.can_id for s in config.lidar.can.sensors] == list(range(0x10, 0x18))
    assert config.lidar.can.sensors[2].yaw_deg == 90.0
    assert config.policy.model == str(EXAMPLE.parent / "policy.onnx")  # relative to the file
    assert config.autopilot.connection == "udpin:0.0.0.0:14550"
    assert config.autopilot.source_component == 191
    assert config.scan.mount_xyz == (0.0, 0.0, 0.1)
    assert config.supervisor.recover_scans == 5
    # the drone checks its autopilot's parameters against the project's file and reads the yaw cap
    assert config.params_check.mode == "warn" and config.params_check.file == ""


def _keys(cls: type, prefix: str = "") -> set[str]:
    out = set()
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        if dataclasses.is_dataclass(tp):
            out |= _keys(tp, f"{prefix}{f.name}.")
        elif typing.get_origin(tp) is tuple and dataclasses.is_dataclass(typing.get_args(tp)[0]):
            out |= _keys(typing.get_args(tp)[0], f"{prefix}{f.name}[].")
        else:
            out.add(prefix + f.name)
    return out


def _toml_keys(data: dict, prefix: str = "") -> set[str]:
    out = set()
    for k, v in data.items():
        if isinstance(v, dict):
            out |= _toml_keys(v, f"{prefix}{k}.")
        elif isinstance(v, list) and v and isinstance(v[0], dict):
            for item in v:
                out |= _toml_keys(item, f"{prefix}{k}[].")
        else:
            out.add(prefix + k)
    return out


def test_example_documents_every_key():
    documented = _toml_keys(load_toml(EXAMPLE))
    assert documented == _keys(CompanionConfig)


def test_defaults_and_overrides(tmp_path):
    path = _write(tmp_path, "")
    config = load_config(path, ["shield.max_speed=1.0", "autopilot.connect=tcp:127.0.0.1:5760"])
    assert config.shield.max_speed == 1.0
    assert config.autopilot.connection == "tcp:127.0.0.1:5760"
    assert config.lidar.source == "velodyne" and config.params_check.mode == "off"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[shield]\nmax_sped = 1.0\n", r"shield\.max_sped: unknown config key"),
        ("[shield]\nmover_speed = -1.5\n", r"^shield\.mover_speed: -1\.5 is below the minimum 0\.0$"),
        ("[supervisor]\nrecover_scans = 2.5\n", r"supervisor\.recover_scans: expected an integer"),
        ("[lidar.velodyne]\nport = 70000\n", r"lidar\.velodyne\.port: 70000 is above the maximum 65535"),
        ("[autopilot]\ntype = \"betaflight\"\n", r"autopilot\.type: must be one of 'ardupilot', 'px4'"),
        ("[scan]\nmin_range = 3.0\nmax_range = 2.0\n", r"scan: min_range 3\.0 must be below max_range 2\.0"),
        ("[lidar]\nsource = \"can\"\n", r"lidar: source is 'can' but can\.sensors lists no rangefinder"),
        ("[[lidar.can.sensors]]\ncan_id = 3\n[[lidar.can.sensors]]\ncan_id = 3\n",
         r"lidar\.can: sensors: CAN id 0x3 is used more than once"),
        ("[[lidar.can.sensors]]\ncan_id = 3\nyaw = 4.0\n",
         r"lidar\.can\.sensors\[0\]\.yaw: unknown config key"),
        ("[autopilot]\ntype = \"px4\"\nconnect = \"udpin:0.0.0.0:99999\"\n",
         r"autopilot: connect: .*'udpin:0\.0\.0\.0:99999': port '99999' is not a port number 1-65535"),
        ("[autopilot]\nconnect = \"udpin//0.0.0.0:14550\"\n", r"autopilot: connect: .*unknown scheme"),
        ("[params_check]\ntimeout = 0.5\n", r"params_check\.timeout: 0\.5 is below the minimum 1"),
        ("[goal.route_planner]\npreferred_clearance = 0.1\n",
         r"goal\.route_planner: preferred_clearance 0\.1 must be at least blocked_clearance 0\.4"),
        ("[goal.route_planner]\nreplan_every = 0\n",
         r"goal\.route_planner\.replan_every: 0 is below the minimum 1"),
        ("[goal.route_planner]\nunseen_cost = 0.5\n",
         r"goal\.route_planner\.unseen_cost: 0\.5 is below the minimum 1"),
        ("[goal.route_planner]\nswitch_margin = -0.5\n",
         r"goal\.route_planner\.switch_margin: -0\.5 is below the minimum 0"),
        ("movers = true\n[goal]\nsource = \"mission\"\n[tracking]\nenabled = false\n",
         r"^CompanionConfig: policy\.movers are the tracker's: it needs tracking\.enabled = true$"),
        ("movers = true\n",
         r"^CompanionConfig: policy\.movers needs a goal source \(goal\.source = \"none\"\): the tracker"),
    ],
)
def test_mistakes_name_the_key(tmp_path, text, message):
    with pytest.raises(UserError, match=message):
        load_config(_write(tmp_path, text))


def test_model_is_required(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text("[shield]\nmax_speed = 1.0\n")
    with pytest.raises(UserError, match=r"^policy\.model: required"):
        load_config(path)


def test_bad_override_names_the_key(tmp_path):
    with pytest.raises(UserError, match=r"shield\.max_speed: expected a number"):
        load_config(_write(tmp_path, ""), ["shield.max_speed=fast"])
    with pytest.raises(UserError, match=r"policy\.stack: 0 is below the minimum 1"):
        load_config(_write(tmp_path, ""), ["policy.stack=0"])


def test_missing_file(tmp_path):
    with pytest.raises(UserError, match=r"^config file .*nope\.toml: file not found$"):
        load_config(tmp_path / "nope.toml")


def test_absolute_and_home_paths_are_kept(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text('[policy]\nmodel = "/opt/avoid/policy.onnx"\n[params_check]\nmode = "warn"\n'
                    'file = "~/copter.parm"\n')
    config = load_config(path)
    assert config.policy.model == "/opt/avoid/policy.onnx"
    assert config.params_check.file == str(Path.home() / "copter.parm")
    assert config.params_check.mode == "warn"


def _float_keys(cls: type, prefix: str = "") -> list[tuple[str, int | None]]:
    """(dotted key, tuple length or None) of every float key, sensors' through one [[table]] item."""
    out: list[tuple[str, int | None]] = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        tp, args = hints[f.name], typing.get_args(hints[f.name])
        if dataclasses.is_dataclass(tp):
            out += _float_keys(tp, f"{prefix}{f.name}.")
        elif typing.get_origin(tp) is tuple and args and dataclasses.is_dataclass(args[0]):
            out += _float_keys(args[0], f"{prefix}{f.name}[0].")
        elif tp is float:
            out.append((prefix + f.name, None))
        elif typing.get_origin(tp) is tuple and args and all(a is float for a in args):
            out.append((prefix + f.name, len(args)))
    return out


FLOAT_KEYS = _float_keys(CompanionConfig)
#: what a [[table]] item needs besides the key under test
REQUIRED_ITEM_KEYS = {"lidar.can.sensors": "can_id = 1, "}


def _override(key: str, length: int | None, value: str) -> str:
    """An override setting ``key`` to ``value`` (tuples: the first item; sensors: one whole table)."""
    item = f"[{value}{', 0.0' * (length - 1)}]" if length else value
    if "[0]." in key:
        table, _, name = key.partition("[0].")
        required = REQUIRED_ITEM_KEYS.get(table, "")
        return f"{table}=[{{{required}{name} = {item}}}]"
    return f"{key}={item}"


def test_every_float_key_is_found():
    keys = {k for k, _ in FLOAT_KEYS}
    assert {"shield.estop_distance", "scan.slice_height", "scan.mount_xyz", "scan.mount_rpy_deg",
            "runtime.heartbeat_interval", "lidar.can.sensors[0].yaw_deg"} <= keys
    assert len(keys) >= 25


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "+nan"])
@pytest.mark.parametrize(("key", "length"), FLOAT_KEYS, ids=[k for k, _ in FLOAT_KEYS])
def test_every_float_key_refuses_nan_and_infinity(tmp_path, key, length, value):
    """NaN passes every comparison with a bound (issue 14: shield.estop_distance=nan flew at a wall)."""
    named = re.escape(f"{key}[0]" if length else key)
    with pytest.raises(UserError, match=rf"^{named}: expected a finite number, got [-+]?(nan|inf)$"):
        load_config(_write(tmp_path, ""), [_override(key, length, value)])


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("scan.mount_xyz=[0.0, 1e30, 0.0]", r"scan\.mount_xyz\[1\]: 1e\+30 is above the maximum 2\.0"),
        ("scan.mount_xyz=[-2.5, 0.0, 0.0]", r"scan\.mount_xyz\[0\]: -2\.5 is below the minimum -2\.0"),
        ("scan.mount_rpy_deg=[0.0, 0.0, 720.0]", r"scan\.mount_rpy_deg\[2\]: 720\.0 is above the max"),
        ("lidar.velodyne.sensor_ip=\"192.168.1.300\"", r"lidar\.velodyne: sensor_ip: '192\.168\.1\.300'"),
        ("policy.sha256=\"abc\"", r"policy: sha256: 'abc' is not 64 hexadecimal digits"),
    ],
)
def test_mount_bounds_sensor_ip_and_model_hash_are_checked(tmp_path, override, message):
    with pytest.raises(UserError, match=message):
        load_config(_write(tmp_path, ""), [override])


def test_mount_within_bounds_and_sensor_ip_load(tmp_path):
    config = load_config(_write(tmp_path, ""), ["scan.mount_rpy_deg=[180.0, -10.0, -180.0]",
                                                "lidar.velodyne.sensor_ip=\"192.168.1.201\"",
                                                f"policy.sha256=\"{'Ab' * 32}\""])
    assert config.scan.mount_rpy_deg == (180.0, -10.0, -180.0)
    assert config.lidar.velodyne.sensor_ip == "192.168.1.201"
