"""The generated reference pages name every command line option and every config key the code has."""

from __future__ import annotations

import dataclasses
import sys
import typing
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tools"))
import docs_reference  # noqa: E402

sys.path.remove(str(REPO / "tools"))


@pytest.fixture(scope="module")
def pages() -> dict[str, str]:
    return docs_reference.generate_pages()


@pytest.mark.parametrize("prog", sorted(docs_reference.PROGRAMS))
def test_every_subcommand_and_option_is_in_its_reference_page(prog, pages):
    page = pages[f"ref/{prog}.md"]
    for name, _help, parser in docs_reference._subcommand_parsers(prog):
        assert f"\n## {name}\n" in page
        section = page.split(f"\n## {name}\n", 1)[1].split("\n## ", 1)[0]
        for action in parser._actions:
            for option in action.option_strings:
                if option not in ("-h", "--help"):
                    assert f"`{option}`" in section, f"{prog} {name} {option}"


def _keys(cls: type, table: str = "") -> list[tuple[str, str]]:
    """(table heading, key) of every leaf field of a config dataclass tree."""
    found = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        key = f"{table}.{f.name}" if table else f.name
        args = typing.get_args(tp) if typing.get_origin(tp) in (tuple, list) else ()
        if dataclasses.is_dataclass(tp):
            found += _keys(tp, key)
        elif args and dataclasses.is_dataclass(args[0]):
            found += _keys(args[0], f"[{key}]")
        else:
            found.append((table, f.name))
    return found


@pytest.mark.parametrize("path", sorted(docs_reference.CONFIGS))
def test_every_config_key_is_in_its_reference_page(path, pages):
    page = pages[path]
    for table, dotted in docs_reference.CONFIGS[path][2]:
        for heading, key in _keys(docs_reference._import(dotted), table):
            title = "Top-level keys" if not heading else (
                f"`[[{heading[1:-1]}]]`" if heading.startswith("[") else f"`[{heading}]`")  # fmt: skip
            assert f"## {title}\n" in page, f"{path}: no section {title}"
            section = page.split(f"## {title}\n", 1)[1].split("\n## ", 1)[0]
            assert f"| `{key}` |" in section, f"{path}: {heading}.{key} missing"


def test_a_param_line_and_its_continuation_are_one_description():
    class Documented:
        """Something.

        :param speed: how fast, m/s; the limit
            the autopilot holds
        :param name: what it is called
        """

    assert docs_reference._param_docs(Documented) == {
        "speed": "how fast, m/s; the limit the autopilot holds",
        "name": "what it is called",
    }


def test_the_field_comment_above_a_key_is_its_description():
    assert "net_arch" in docs_reference._comment_docs(docs_reference._import("training.config.PPOConfig"))
