"""The attack bench's long run: chunks appended to a file, resumed without flying them again."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[2] / "bench" / "bench_shield_attack.py"


def _bench(out: Path) -> subprocess.CompletedProcess[str]:
    flags = ["--out", str(out), "--chunk", "1", "--seeds", "1", "--max-steps", "10", "--workers", "1"]
    argv = [sys.executable, str(BENCH), *flags]
    return subprocess.run(argv, capture_output=True, text=True, timeout=240, check=False)


def test_a_chunk_is_flown_once_and_counted_from_the_file(tmp_path: Path) -> None:
    out = tmp_path / "attack.jsonl"
    first = _bench(out)
    assert first.returncode == 0, first.stderr[-2000:]
    chunks = [json.loads(line) for line in out.read_text().splitlines()]
    assert [c["first_seed"] for c in chunks] == [599_000]
    episodes = chunks[0]["episodes"]
    assert {e["gate"] for e in episodes} == {False, True} and len(episodes) == 2 * 9 * 3
    # what tells a collision the promise covers: the velocity error, and whether the gate lost its
    # invariant (best effort); behind the rules alone, the gate never acts
    assert all(e["velocity_error"] > 0.0 for e in episodes)
    assert not any(e["best_effort"] for e in episodes if not e["gate"])
    assert any(e["best_effort"] for e in episodes if e["gate"])
    again = _bench(out)
    assert again.returncode == 0 and "chunk from seed" not in again.stdout
    assert out.read_text().count("\n") == 1  # not flown again
    assert f"{out}: 1 chunks, {9 * 3} episodes behind the gate" in again.stdout


def test_a_line_that_is_not_a_chunk_is_named(tmp_path: Path) -> None:
    out = tmp_path / "attack.jsonl"
    out.write_text('{"first_seed": 599000}\n')
    run = _bench(out)
    assert run.returncode != 0
    assert run.stderr.strip().splitlines()[-1].startswith(f"bench_shield_attack: {out}:1: not a chunk")


def test_a_file_of_other_chunks_is_refused(tmp_path: Path) -> None:
    """Chunks flown with other flags are not mixed into this run's figures."""
    out = tmp_path / "attack.jsonl"
    out.write_text(json.dumps({"first_seed": 599_000, "seeds": 1, "max_steps": 400, "episodes": []}) + "\n")
    run = _bench(out)
    assert run.returncode != 0
    assert "a chunk of 1 seeds at 400 steps (random); this run flies 1 at 10 (random)" in run.stderr
