"""The documentation points only at things inside the repository, and its examples are true."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = [
    "README.md",
    "ARCHITECTURE.md",
    *sorted(str(p.relative_to(REPO)) for p in (REPO / "docs").glob("*.md")),
]
TOP = ("docs/", "flightsim/", "companion/", "training/", "bench/", "firmware_params/", "systemd/", "config/",
       "models/", "tests/", "ci/")  # fmt: skip


def _paths(text: str) -> set[str]:
    """Repository paths written in backticks: `dir/file.ext`, `dir/sub/`, `FILE.md` (no placeholders)."""
    found = set()
    for span in re.findall(r"`([^`\n]+)`", text):
        for word in span.split():
            word = word.rstrip(".,;:)").split("::")[0]
            if any(c in word for c in "<>*{}[]|…$") or "=" in word:
                continue
            named_file = re.search(r"\.\w+$", word) or word.endswith("/")  # not an id like flightsim/X-v0
            if (word.startswith(TOP) and named_file) or re.fullmatch(r"[A-Z_]+\.md", word):
                found.add(word)
    return found


@pytest.mark.parametrize("doc", DOCS)
def test_every_path_a_document_names_exists_in_the_repository(doc):
    text = (REPO / doc).read_text()
    missing = sorted(p for p in _paths(text) if not (REPO / p).exists())
    assert not missing, f"{doc} names files that are not in the repository: {missing}"


@pytest.mark.parametrize("doc", DOCS)
def test_documents_speak_of_nothing_outside_the_repository(doc):
    text = (REPO / doc).read_text()
    assert not re.search(r"(?<![\w/])(shared/|reference/)", text), "points outside the repository"
    assert not re.search(r"\bissue \d", text), "speaks of the tracker's issues, not of the project"


def test_the_world_schema_example_loads(tmp_path):
    from flightsim.worlds.world import load_world

    text = (REPO / "docs" / "worlds.md").read_text()
    example = json.loads(re.search(r"```json\n(.*?)```", text, re.S).group(1))
    path = tmp_path / "example.json"
    path.write_text(json.dumps(example))
    assert load_world(path).name == example["name"]
