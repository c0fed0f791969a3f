"""The results tables, rendered from ``docs/results.json`` so the README and the docs cannot disagree.

``docs/results.json`` holds every headline figure with its value, target, the command that
measured it, the date, the machine and its load. This script renders:

- the README's table (the figures marked ``"readme": true``; figure, value, target, command),
  between the ``<!-- results:begin -->`` and ``<!-- results:end -->`` lines;
- the docs' full table (every figure, with date, machine and load), in place of the
  ``<!-- results:all -->`` line of ``docs/results.md`` (as a MkDocs hook, at build time).

``python tools/gen_results.py`` rewrites the README's table; ``--check`` exits 1 when it is stale.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "docs" / "results.json"
README = REPO / "README.md"
BEGIN, END = "<!-- results:begin -->", "<!-- results:end -->"
ALL_MARKER = "<!-- results:all -->"
#: the README's table may not grow past this
README_MAX_ROWS = 12


def load_results(path: Path = RESULTS) -> dict[str, Any]:
    """The results file, checked: every figure has the fields the tables show."""
    data = json.loads(path.read_text())
    needed = {"id", "readme", "figure", "value", "target", "command", "date", "machine", "load"}
    for i, fig in enumerate(data["figures"]):
        missing = needed - fig.keys()
        if missing:
            raise ValueError(f"{path.name}: figures[{i}] lacks {', '.join(sorted(missing))}")
        if fig["machine"] not in data["machines"] or fig["load"] not in data["loads"]:
            raise ValueError(f"{path.name}: figures[{i}] names an unknown machine or load")
    return data


def _row(cells: list[str]) -> str:
    return "| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |"


def readme_table(data: dict[str, Any]) -> str:
    """The README's results table: one line per figure marked for it."""
    figures = [f for f in data["figures"] if f["readme"]]
    if len(figures) > README_MAX_ROWS:
        raise ValueError(f"{len(figures)} README figures: at most {README_MAX_ROWS}")
    lines = ["| figure | value | target | command |", "| --- | --- | --- | --- |"]
    lines += [_row([f["figure"], f["value"], f["target"], f["command"]]) for f in figures]
    return "\n".join(lines)


def full_table(data: dict[str, Any]) -> str:
    """Every figure, with when, where and under what load it was measured, and its note."""
    lines = [
        "| figure | value | target | command | measured | note |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for f in data["figures"]:
        when = f"{f['date']}, {f['load']}"
        lines.append(_row([f["figure"], f["value"], f["target"], f["command"], when, f.get("note", "")]))
    lines += ["", "Machines and loads:", ""]
    lines += [f"- **{name}**: {text}" for name, text in data["machines"].items()]
    lines += [f"- **{name}**: {text}" for name, text in data["loads"].items()]
    return "\n".join(lines)


def readme_with_table(readme: str, table: str) -> str:
    """``readme`` with the text between the markers replaced by ``table``."""
    head, sep, rest = readme.partition(BEGIN)
    _, sep2, tail = rest.partition(END)
    if not sep or not sep2:
        raise ValueError(f"README.md lacks the {BEGIN} / {END} lines")
    return f"{head}{BEGIN}\n{table}\n{END}{tail}"


# ---------------------------------------------------------------- MkDocs hook


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    """MkDocs hook: the full results table in place of its marker."""
    if ALL_MARKER in markdown:
        markdown = markdown.replace(ALL_MARKER, full_table(load_results()))
    return markdown


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Render the README's results table from docs/results.json.")
    parser.add_argument(
        "--check", action="store_true", help="exit 1 if README.md's table is stale; write nothing"
    )
    args = parser.parse_args(argv)
    try:
        text = README.read_text()
        updated = readme_with_table(text, readme_table(load_results()))
    except (OSError, ValueError, KeyError) as exc:
        print(f"gen_results: error: {exc}", file=sys.stderr)
        return 2
    if args.check:
        if updated != text:
            print("gen_results: README.md's results table is stale: run python tools/gen_results.py",
                  file=sys.stderr)
            return 1
        return 0
    README.write_text(updated)
    return 0


if __name__ == "__main__":
    sys.exit(main())
