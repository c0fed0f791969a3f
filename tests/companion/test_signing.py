"""The signing key file and the config keys that switch signing on: every mistake is one line."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from companion.autopilot.signing import KEY_LENGTH, load_signing_key, write_signing_key
from companion.common.errors import UserError
from companion.config import load_config
from tests.companion.companion_process import run_to_exit

KEY_HEX = bytes(range(1, 33)).hex()


def _key_file(tmp_path: Path, text: str, mode: int = 0o600, name: str = "signing.key") -> Path:
    path = tmp_path / name
    path.write_text(text)
    path.chmod(mode)
    return path


def test_a_good_key_file_loads(tmp_path):
    assert load_signing_key(_key_file(tmp_path, f"  {KEY_HEX.upper()}\n")) == bytes(range(1, 33))
    assert load_signing_key(_key_file(tmp_path, KEY_HEX, 0o400, "ro.key")) == bytes(range(1, 33))


def test_write_signing_key_is_owner_only_and_round_trips(tmp_path):
    key = write_signing_key(tmp_path / "new.key")
    assert len(key) == KEY_LENGTH
    assert (tmp_path / "new.key").stat().st_mode & 0o777 == 0o600
    assert load_signing_key(tmp_path / "new.key") == key
    with pytest.raises(FileExistsError):
        write_signing_key(tmp_path / "new.key")


@pytest.mark.parametrize(
    ("text", "mode", "message"),
    [
        (KEY_HEX, 0o644, r"readable or writable by group/others \(mode 0644\); run chmod 600"),
        (KEY_HEX, 0o620, r"mode 0620"),
        (KEY_HEX[:-2], 0o600, r"expected 64 hexadecimal digits, found 62"),
        (KEY_HEX + "00", 0o600, r"expected 64 hexadecimal digits, found 66"),
        ("zz" * 32, 0o600, r"expected 64 hexadecimal digits on one line"),
        ("é" * 32, 0o600, r"expected 64 hexadecimal digits on one line"),
        ("00" * 32, 0o600, r"all-zero key means 'signing off'"),
        ("", 0o600, r"found 0"),
    ],
)
def test_bad_key_files_name_the_file_and_the_problem(tmp_path, text, mode, message):
    path = _key_file(tmp_path, text, mode)
    with pytest.raises(UserError, match=rf"^autopilot\.signing_key: {tmp_path}/signing\.key: .*{message}"):
        load_signing_key(path)


def test_missing_directory_and_unreadable_key_files(tmp_path):
    with pytest.raises(UserError, match=r"signing_key: .*missing\.key: cannot read: No such file"):
        load_signing_key(tmp_path / "missing.key")
    with pytest.raises(UserError, match=r"not a regular file"):
        load_signing_key(tmp_path)
    if os.geteuid() != 0:  # root reads anything
        path = _key_file(tmp_path, KEY_HEX, 0o000, "locked.key")
        with pytest.raises(UserError, match=r"locked\.key: cannot read: Permission denied"):
            load_signing_key(path)


def _config(tmp_path: Path, autopilot: str) -> Path:
    path = tmp_path / "companion.toml"
    path.write_text(f'[policy]\nmodel = "policy.onnx"\n[autopilot]\n{autopilot}\n')
    return path


def test_config_resolves_the_key_next_to_the_config_file(tmp_path):
    _key_file(tmp_path, KEY_HEX)
    config = load_config(_config(tmp_path, 'signing_key = "signing.key"\nsystem_id = 3\ncomponent_id = 1'))
    assert config.autopilot.signing_key == str(tmp_path / "signing.key")
    assert (config.autopilot.system_id, config.autopilot.component_id) == (3, 1)
    defaults = load_config(_config(tmp_path, ""))
    assert defaults.autopilot.signing_key == ""
    assert (defaults.autopilot.system_id, defaults.autopilot.component_id) == (1, 1)


def test_config_refuses_a_bad_key_file_at_load(tmp_path):
    _key_file(tmp_path, KEY_HEX, 0o644)
    with pytest.raises(UserError, match=r"autopilot\.signing_key: .*signing\.key: readable"):
        load_config(_config(tmp_path, 'signing_key = "signing.key"'))


def test_px4_takes_a_signing_key_too(tmp_path):
    """MAVSDK cannot sign, but the PX4 link carries MAVSDK's frames through its own endpoint, which does."""
    _key_file(tmp_path, KEY_HEX)
    config = load_config(_config(tmp_path, 'type = "px4"\nsigning_key = "signing.key"'))
    assert config.autopilot.signing_key == str(tmp_path / "signing.key")


@pytest.mark.parametrize("key", ["system_id = 0", "component_id = 256", 'system_id = "1"'])
def test_autopilot_ids_are_checked(tmp_path, key):
    with pytest.raises(UserError, match=r"autopilot\.(system_id|component_id)"):
        load_config(_config(tmp_path, key))


def test_the_companion_exits_2_on_a_bad_key_file(tmp_path):
    _key_file(tmp_path, KEY_HEX, 0o664)
    result = run_to_exit(["run", "--config", str(_config(tmp_path, 'signing_key = "signing.key"'))])
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "autopilot.signing_key" in lines[0] and "Traceback" not in result.stderr
