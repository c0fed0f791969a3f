"""Config, world and model files that cannot be read or parsed: one line naming the file, exit 2.

Issue 14 found tracebacks for a config holding byte 0xFF (UnicodeDecodeError), a config path that is a
directory or a symlink loop, an ONNX model whose metadata holds invalid UTF-8, and a world of 100,000
nested brackets (RecursionError in load_world). Each case runs the real command line where one reads
that file, and the shared reader (companion.common.userfile) where the case is about the file itself.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from companion.common.errors import UserError
from companion.common.tomlconfig import load_toml
from companion.common.userfile import load_user_file, read_user_bytes
from companion.guidance.policy import OnnxPolicy, PolicySpec
from flightsim.worlds.world import load_world
from tests.companion.companion_process import REPO, free_udp_port, run_to_exit, write_config
from tests.onnx_models import write_policy

DEEP = 100_000


def _one_line_exit_2(result: subprocess.CompletedProcess[str], prog: str, *words: str) -> str:
    assert result.returncode == 2, result.stderr[-3000:]
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr[-3000:]
    assert lines[0].startswith(f"{prog}: error: ")
    for word in words:
        assert word in lines[0], lines[0]
    return lines[0]


def _config_cases(tmp_path: Path) -> dict[str, tuple[Path, str]]:
    """A config path for each way a file can be unreadable, and the problem the message must say."""
    cases: dict[str, tuple[Path, str]] = {}
    good = write_config(tmp_path, tmp_path / "m.onnx", free_udp_port(), free_udp_port()).read_bytes()
    (tmp_path / "ff.toml").write_bytes(good[:40] + b"\xff" + good[40:])
    cases["byte 0xFF"] = (tmp_path / "ff.toml", "not UTF-8 text (byte 0xff at offset 40)")
    (tmp_path / "dir.toml").mkdir()
    cases["a directory"] = (tmp_path / "dir.toml", "is a directory")
    os.symlink(tmp_path / "loop-b.toml", tmp_path / "loop-a.toml")
    os.symlink(tmp_path / "loop-a.toml", tmp_path / "loop-b.toml")
    cases["a symlink loop"] = (tmp_path / "loop-a.toml", "is a symlink loop")
    os.mkfifo(tmp_path / "fifo.toml")
    cases["a FIFO (would block)"] = (tmp_path / "fifo.toml", "is not a regular file")
    (tmp_path / "deep.toml").write_text("a = " + "[" * DEEP + "]" * DEEP + "\n")
    cases["100,000 nested arrays"] = (tmp_path / "deep.toml", "nested too deeply to parse")
    (tmp_path / "bad.toml").write_text("[policy\n")
    cases["not TOML"] = (tmp_path / "bad.toml", "not valid TOML")
    cases["missing"] = (tmp_path / "nope.toml", "file not found")
    cases["a file in the path"] = (tmp_path / "ff.toml" / "x.toml", "a part of the path is not a directory")
    return cases


CONFIG_CASES = ["byte 0xFF", "a directory", "a symlink loop", "a FIFO (would block)", "100,000 nested arrays",
                "not TOML", "missing", "a file in the path"]


@pytest.mark.parametrize("case", CONFIG_CASES)
def test_unreadable_config_is_one_line_exit_2(tmp_path: Path, case: str) -> None:
    path, problem = _config_cases(tmp_path)[case]
    result = run_to_exit(["run", "--config", str(path)])  # first: with a timeout (a FIFO hung before)
    _one_line_exit_2(result, "avoid-companion", str(path), problem)
    with pytest.raises(UserError) as info:
        load_toml(path)
    assert str(info.value).startswith(f"config file {path}: {problem}")


def test_unreadable_for_lack_of_permission(tmp_path: Path) -> None:
    """As root every file is readable: then this process reads as user nobody (seteuid) meanwhile."""
    directory = Path(tempfile.mkdtemp(prefix="userfile-"))  # not under pytest's private tmp directory
    try:
        directory.chmod(0o755)
        path = directory / "secret.toml"
        path.write_text('[policy]\nmodel = "m.onnx"\n')
        path.chmod(0o000)
        root = os.geteuid() == 0
        if root:
            os.seteuid(65534)
        try:
            with pytest.raises(UserError) as info:
                load_toml(path)
        finally:
            if root:
                os.seteuid(0)
        assert str(info.value) == f"config file {path}: permission denied"
    finally:
        shutil.rmtree(directory)


def test_world_files_that_cannot_be_read_are_one_line(tmp_path: Path) -> None:
    deep = tmp_path / "deep.json"
    deep.write_text("[" * DEEP + "]" * DEEP)
    with pytest.raises(UserError, match=r"^world .*deep\.json: nested too deeply to parse$"):
        load_world(deep)
    (tmp_path / "ff.json").write_bytes(b'{"name": "\xff"}')
    with pytest.raises(UserError, match=r"^world .*ff\.json: not UTF-8 text \(byte 0xff at offset 10\)$"):
        load_world(tmp_path / "ff.json")
    (tmp_path / "dir.json").mkdir()
    with pytest.raises(UserError, match=r"^world .*dir\.json: is a directory, not a file$"):
        load_world(tmp_path / "dir.json")
    os.symlink(tmp_path / "loop.json", tmp_path / "loop.json")
    with pytest.raises(UserError, match=r"^world .*loop\.json: is a symlink loop$"):
        load_world(tmp_path / "loop.json")
    # and on the command line that flies a world file
    result = subprocess.run([sys.executable, "-m", "flightsim", "fly", "--world", str(deep)], cwd=REPO,
                            capture_output=True, text=True, timeout=120)
    _one_line_exit_2(result, "avoid-sim", str(deep), "nested too deeply to parse")


def test_model_with_invalid_utf8_metadata_is_one_line(tmp_path: Path) -> None:
    data = write_policy(tmp_path / "m.onnx").read_bytes()
    assert data.count(b"ccw-from-forward-1deg") == 1
    path = tmp_path / "bad-meta.onnx"
    path.write_bytes(data.replace(b"ccw-from-forward-1deg", b"ccw-from-forward-1de\xff"))
    with pytest.raises(UserError, match=r"^policy model .*bad-meta\.onnx: metadata is not UTF-8 text"):
        OnnxPolicy(path, PolicySpec())
    config = write_config(tmp_path, path, free_udp_port(), free_udp_port())
    _one_line_exit_2(run_to_exit(["run", "--config", str(config)]), "avoid-companion", "bad-meta.onnx",
                     "metadata is not UTF-8")


@pytest.mark.parametrize("case", ["a directory", "a symlink loop", "a FIFO (would block)"])
def test_model_path_that_is_not_a_file_is_one_line(tmp_path: Path, case: str) -> None:
    path, problem = _config_cases(tmp_path)[case]
    config = write_config(tmp_path, path, free_udp_port(), free_udp_port())
    _one_line_exit_2(run_to_exit(["run", "--config", str(config)]), "avoid-companion", str(path), problem)


def test_model_hash_is_checked_when_configured(tmp_path: Path) -> None:
    model = write_policy(tmp_path / "m.onnx", spec=PolicySpec())
    digest = hashlib.sha256(model.read_bytes()).hexdigest()
    assert OnnxPolicy(model, PolicySpec(), sha256=digest.upper()).sha256 == digest
    corrupted = bytearray(model.read_bytes())
    corrupted[-5] ^= 0x01  # one bit of one weight
    model.write_bytes(bytes(corrupted))
    with pytest.raises(UserError, match=rf"sha256 \w{{64}} is not the configured policy\.sha256 {digest}"):
        OnnxPolicy(model, PolicySpec(), sha256=digest)
    config = write_config(tmp_path, model, free_udp_port(), free_udp_port())
    result = run_to_exit(["run", "--config", str(config), f'policy.sha256="{digest}"'])
    _one_line_exit_2(result, "avoid-companion", "is not the configured policy.sha256")


def test_reader_limits_size_and_keeps_bytes(tmp_path: Path) -> None:
    path = tmp_path / "big.bin"
    path.write_bytes(b"x" * 2000)
    assert read_user_bytes(path, "thing", max_bytes=2000) == b"x" * 2000
    with pytest.raises(UserError, match=r"^thing .*big\.bin: is 2000 bytes, larger than the 1999 allowed$"):
        read_user_bytes(path, "thing", max_bytes=1999)


    def parse(text: str) -> None:
        raise ValueError("no y here\nand a second line")

    with pytest.raises(UserError, match=r"^thing .*big\.bin: no y here$"):
        load_user_file(path, "thing", parse)
