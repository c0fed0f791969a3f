"""The documentation points only at things inside the repository, stays short and without run
history, and its examples and tables are true."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = [
    "README.md",
    "ARCHITECTURE.md",
    "CHANGELOG.md",
    *sorted(str(p.relative_to(REPO)) for p in (REPO / "docs").glob("*.md")),
]
TOP = ("docs/", "flightsim/", "companion/", "training/", "bench/", "firmware_params/", "systemd/", "config/",
       "models/", "tests/", "ci/", "tools/")  # fmt: skip
#: a newcomer reads these whole
README_MAX_BYTES = 15_000
GOAL_POLICY_MAX_BYTES = 20_000
#: a date in a sentence is run history: it belongs in git, CHANGELOG.md or docs/results.json
DATE = re.compile(r"\b20\d\d-\d\d-\d\d\b")


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


def test_the_readme_is_short():
    size = (REPO / "README.md").stat().st_size
    assert size <= README_MAX_BYTES, f"README.md is {size} bytes; at most {README_MAX_BYTES}"


def test_how_the_shipped_policy_was_made_is_one_short_page():
    size = (REPO / "docs" / "goal-policy.md").stat().st_size
    assert size <= GOAL_POLICY_MAX_BYTES, (
        f"docs/goal-policy.md is {size} bytes; at most {GOAL_POLICY_MAX_BYTES}"
    )


@pytest.mark.parametrize(
    "path",
    ["README.md", "config/companion.example.toml",
     *sorted(str(p.relative_to(REPO)) for p in (REPO / "docs").glob("*.md")),
     *sorted(str(p.relative_to(REPO)) for p in (REPO / "training" / "configs").glob("*.toml"))],
)  # fmt: skip
def test_readme_docs_and_config_comments_carry_no_run_history(path):
    text = (REPO / path).read_text()
    if path.endswith(".toml"):
        text = "\n".join(line for line in text.splitlines() if line.lstrip().startswith("#"))
    dated = sorted(set(DATE.findall(text)))
    assert not dated, f"{path} dates its text ({', '.join(dated)}): history belongs in git and CHANGELOG.md"
    assert not re.search(r"\bsession\b", text, re.I), f"{path} speaks of work sessions"


def test_the_readme_results_table_is_the_one_rendered_from_the_results_file():
    sys.path.insert(0, str(REPO / "tools"))
    try:
        import gen_results
    finally:
        sys.path.remove(str(REPO / "tools"))
    data = gen_results.load_results()
    table = gen_results.readme_table(data)
    readme = (REPO / "README.md").read_text()
    assert gen_results.readme_with_table(readme, table) == readme, (
        "README.md's results table differs from docs/results.json: run python tools/gen_results.py"
    )
    assert len(table.splitlines()) - 2 <= gen_results.README_MAX_ROWS
    for figure in data["figures"]:
        assert re.fullmatch(r"20\d\d-\d\d-\d\d", figure["date"]), figure["id"]


def test_the_readme_test_command_is_the_one_ci_runs():
    readme = (REPO / "README.md").read_text()
    command = "pip install -e '.[train,test]' && ruff check . && pytest"
    assert f"```sh\n{command}\n```" in readme
    assert command in (REPO / ".ci" / "run").read_text()


def test_every_shell_block_says_whether_the_command_test_runs_it():
    """A new command in the docs is either run by tests/test_doc_commands.py or says why not."""
    unmarked = []
    for doc in ["README.md", *sorted(str(p.relative_to(REPO)) for p in (REPO / "docs").glob("*.md"))]:
        lines = (REPO / doc).read_text().splitlines()
        for i, line in enumerate(lines):
            if line in ("```sh", "```bash") and not re.fullmatch(r"<!-- (run|norun: .+) -->", lines[i - 1]):
                unmarked.append(f"{doc}:{i + 1}")
    assert not unmarked, f"shell blocks without <!-- run --> or <!-- norun: why -->: {unmarked}"


def test_the_docs_site_builds_without_a_warning(tmp_path):
    """``mkdocs build --strict``: broken links and anchors, pages left out of the nav, and reference
    pages the generator cannot build all fail it."""
    result = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=REPO, capture_output=True, text=True, timeout=300,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    for page in ("ref/avoid-sim", "ref/avoid-train", "ref/avoid-companion", "ref/companion-config",
                 "ref/training-config", "results"):  # fmt: skip
        assert (tmp_path / "site" / page / "index.html").is_file(), page
