"""A project command started as a terminal starts a foreground job, for the Ctrl-C tests: its own
process group (``os.killpg(proc.pid, SIGINT)`` is the terminal's Ctrl-C) and SIGINT handled."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _default_sigint() -> None:
    # a shell's background jobs start with SIGINT ignored, and children inherit it: undo that
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def start_foreground(module: str, *args: str) -> subprocess.Popen[str]:
    """``python -m module args...`` from the checkout, its output piped as text."""
    return subprocess.Popen(
        [sys.executable, "-m", module, *args],
        cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=_default_sigint,
        start_new_session=True,
    )


def running_in_group(pgid: int) -> list[str]:
    """Processes of group ``pgid`` still running, by command name (zombies left to an init that
    does not reap them, as in a container, have ended)."""
    running = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
        except OSError:  # ended while listed
            continue
        name, fields = text[text.index("(") + 1 : text.rindex(")")], text[text.rindex(")") + 2 :].split()
        if int(fields[2]) == pgid and fields[0] not in "ZX":
            running.append(name)
    return running


def ctrl_c_once_flying(proc: subprocess.Popen[str], workdir: Path, flights: int = 1) -> tuple[str, str]:
    """Once ``flights`` companions under ``workdir`` run (their ``companion.log`` says so) and have
    had time to take off, Ctrl-C; the command's (stdout, stderr) once it has exited."""
    deadline = time.monotonic() + 120
    while proc.poll() is None and time.monotonic() < deadline:
        logs = [log for log in workdir.rglob("companion.log") if "companion running" in log.read_text()]
        if len(logs) >= flights:
            break
        time.sleep(0.2)
    assert proc.poll() is None, proc.communicate()
    time.sleep(2.0)  # taking off
    os.killpg(proc.pid, signal.SIGINT)
    return proc.communicate(timeout=60)
