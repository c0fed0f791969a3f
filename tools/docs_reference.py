"""The docs site's reference pages, generated from the code so they cannot go stale.

Every command line option comes from the argparse parsers the three programs build (each
subcommand module's ``configure_parser``), and every config key from the config dataclasses:
its type, default and range from the field, its meaning from the class docstring's ``:param:``
line or the ``#:`` comment above the field.

Used two ways: as a MkDocs hook (``hooks:`` in ``mkdocs.yml``; the pages, and the repository's
``CHANGELOG.md`` as ``changelog.md``, are added to the build, never written into ``docs/``), and
as a script that writes them to a directory to read them: ``python tools/docs_reference.py OUT``.
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import dataclasses
import importlib
import inspect
import re
import sys
import textwrap
import types
import typing
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]

#: program -> (module whose SUBCOMMANDS table and main() define it, one line on what it is for)
PROGRAMS: dict[str, tuple[str, str]] = {
    "avoid-sim": ("flightsim.__main__", "the simulator: SITL flights, the demo, worlds and reports"),
    "avoid-train": ("training.__main__", "training, evaluation, tracing and ONNX export"),
    "avoid-companion": ("companion.__main__", "the process on the drone, its parameter check and replay"),
}

#: page -> (title, introduction, [(table name, dotted class path)])
CONFIGS: dict[str, tuple[str, str, list[tuple[str, str]]]] = {
    "ref/companion-config.md": (
        "Companion config keys",
        "The keys of the companion's TOML file (`config/companion.example.toml` is a commented "
        "example). Every key is optional except `policy.model`. A key can be overridden on the "
        "command line as `table.key=value` (the value is parsed as TOML). Relative paths in the "
        "file are relative to the file.",
        [("", "companion.config.CompanionConfig")],
    ),
    "ref/training-config.md": (
        "Training config keys",
        "The keys of a training config (`training/configs/*.toml`), overridable on the command "
        "line as `key=value`. The `[env]` table is the simulator's environment config: "
        "`EnvConfig` for `flightsim/LidarAvoid-v0`, `NavEnvConfig` (which adds to it) for "
        "`flightsim/LidarNav-v0`.",
        [
            ("", "training.config.TrainConfig"),
            ("env", "flightsim.envs.nav_env.NavEnvConfig"),
        ],
    ),
}


def _import(dotted: str) -> Any:
    module, _, name = dotted.rpartition(".")
    return getattr(importlib.import_module(module), name)


def _md(text: str) -> str:
    """One table cell: no newlines, no bare pipes, and ``<name>`` outside code spans shown, not
    read as HTML."""
    parts = " ".join(text.split()).replace("|", "\\|").split("`")
    parts[::2] = [p.replace("<", "&lt;").replace(">", "&gt;") for p in parts[::2]]
    return "`".join(parts)


def _rst_to_md(text: str) -> str:
    """Docstring markup to Markdown: ``x`` and :role:`x` become `x`."""
    text = re.sub(r":\w+:`~?([^`]+)`", r"`\1`", text)
    return text.replace("``", "`")


# ---------------------------------------------------------------- command lines


def _subcommand_parsers(prog: str) -> list[tuple[str, str, argparse.ArgumentParser]]:
    """(name, one-line help, parser) of every subcommand, built as ``companion.cli.run_cli`` builds them."""
    module = importlib.import_module(PROGRAMS[prog][0])
    found = []
    for name, (module_name, help_text) in module.SUBCOMMANDS.items():
        parser = argparse.ArgumentParser(prog=f"{prog} {name}", description=help_text)
        importlib.import_module(module_name).configure_parser(parser)
        found.append((name, help_text, parser))
    return found


def _option_row(action: argparse.Action, prog: str) -> str:
    if action.option_strings:
        names = ", ".join(f"`{s}`" for s in action.option_strings)
        takes_value = action.nargs != 0
        if takes_value:
            metavar = action.metavar or (action.dest.upper())
            names += f" `{metavar if isinstance(metavar, str) else ' '.join(metavar)}`"
    else:
        metavar = action.metavar or action.dest
        names = f"`{metavar}`"
    help_text = action.help or ""
    if "%" in help_text:
        params = {**vars(action), "prog": prog}
        params["default"] = action.default
        if action.choices is not None:
            params["choices"] = ", ".join(map(str, action.choices))
        with contextlib.suppress(KeyError, TypeError, ValueError):  # a literal % in the text
            help_text = help_text % params
    if action.choices is not None and not isinstance(action.choices, dict):
        help_text += f" (one of: {', '.join(f'`{c}`' for c in action.choices)})"
    default = action.default
    empty = isinstance(default, (list, tuple, set, frozenset, dict)) and not default
    if default in (None, False, argparse.SUPPRESS) or action.nargs == 0 or empty:
        shown = ""
    else:
        shown = '`""`' if default == "" else f"`{default}`"
    return f"| {names} | {shown} | {_md(help_text)} |"


def cli_page(prog: str) -> str:
    """The reference page of one program: every subcommand's usage and options."""
    purpose = PROGRAMS[prog][1]
    lines = [
        f"# `{prog}`",
        "",
        f"{purpose[0].upper()}{purpose[1:]}. Generated from the program's argparse parsers.",
        f"`{prog} -v COMMAND ...` logs debug messages. A bad argument or input file is one line "
        f"`{prog}: error: ...` and exit status 2.",
        "",
    ]
    for name, help_text, parser in _subcommand_parsers(prog):
        usage = " ".join(parser.format_usage().removeprefix("usage: ").split())
        lines += [
            f"## {name}",
            "",
            _md(help_text[0].upper() + help_text[1:]) + ".",
            "",
            "```text",
            textwrap.fill(usage, 100, subsequent_indent="    ", break_on_hyphens=False),
            "```",
            "",
            "| option | default | what it does |",
            "| --- | --- | --- |",
        ]
        lines += [_option_row(a, prog) for a in parser._actions if not isinstance(a, argparse._HelpAction)]
        lines.append("")
    return "\n".join(lines)


# ---------------------------------------------------------------- config keys


def _param_docs(cls: type) -> dict[str, str]:
    """``:param name: text`` of the class docstring (and its bases'), continuation lines joined."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        doc = inspect.getdoc(klass) if klass.__dict__.get("__doc__") else None
        if not doc:
            continue
        for match in re.finditer(r"^:param (\w+):(.*(?:\n(?!:)(?:[ \t]+.*|)\S?.*)*)", doc, re.M):
            text = match.group(2)
            text = text.split("\n\n")[0]
            docs[match.group(1)] = " ".join(text.split())
    return docs


def _comment_docs(cls: type) -> dict[str, str]:
    """``#:`` comments right above a field in the class body (and its bases')."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass) or klass.__module__ == "builtins":
            continue
        try:
            source_lines, _ = inspect.getsourcelines(klass)
        except (OSError, TypeError):
            continue
        source = textwrap.dedent("".join(source_lines))
        lines = source.splitlines()
        tree = ast.parse(source)
        body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
        for node in body:
            if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
                comment = []
                i = node.lineno - 2
                while i >= 0 and lines[i].strip().startswith("#:"):
                    comment.insert(0, lines[i].strip()[2:].strip())
                    i -= 1
                if comment:
                    docs[node.target.id] = " ".join(comment)
    return docs


def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin is typing.Literal:
        return " \\| ".join(f'`"{a}"`' if isinstance(a, str) else f"`{a}`" for a in args)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in args if a is not type(None)) + " (optional)"
    if origin in (tuple, list):
        inner = [a for a in args if a is not Ellipsis]
        return "list of " + (_type_name(inner[0]) if inner else "values")
    if origin is dict:
        return "table"
    return {bool: "bool", int: "int", float: "float", str: "string"}.get(tp, getattr(tp, "__name__", str(tp)))


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{}" if not value else str(value)
    if value is None:
        return "(none)"
    return repr(value)


def _is_dataclass_type(tp: Any) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def _table_sections(cls: type, table: str) -> list[str]:
    """Markdown sections for ``cls`` as the TOML table ``table``, then its sub-tables."""
    hints = typing.get_type_hints(cls)
    docs = {**_param_docs(cls), **_comment_docs(cls)}
    rows, children = [], []
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        key = f"{table}.{f.name}" if table else f.name
        if _is_dataclass_type(tp):
            children.append((key, tp, docs.get(f.name, "")))
            continue
        args = typing.get_args(tp) if typing.get_origin(tp) in (tuple, list) else ()
        item = args[0] if args else None
        if _is_dataclass_type(item):
            children.append((f"[{key}]", item, docs.get(f.name, "")))
            continue
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            default = dataclasses.MISSING
        shown = "(required)" if default is dataclasses.MISSING else _toml_value(default)
        bounds = []
        if "min" in f.metadata:
            bounds.append(f"≥ {f.metadata['min']}")
        if "max" in f.metadata:
            bounds.append(f"≤ {f.metadata['max']}")
        kind = _type_name(tp) + (f", {' and '.join(bounds)}" if bounds else "")
        rows.append(f"| `{f.name}` | {kind} | `{shown}` | {_md(_rst_to_md(docs.get(f.name, '')))} |")
    sections = []
    if rows:
        heading = f"[[{table[1:-1]}]]" if table.startswith("[") else (f"[{table}]" if table else "top level")
        intro = _rst_to_md((inspect.getdoc(cls) or "").split("\n\n")[0]) if cls.__doc__ else ""
        sections += [f"## `{heading}`" if table else "## Top-level keys", ""]
        if intro and not intro.startswith(":param"):
            sections += [_md(intro), ""]
        sections += ["| key | type | default | what it does |", "| --- | --- | --- | --- |", *rows, ""]
    for key, child, doc in children:
        child_sections = _table_sections(child, key)
        if doc and child_sections:
            child_sections.insert(2, _md(_rst_to_md(doc)) + "\n")
        sections += child_sections
    return sections


def _default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    return f.default_factory() if f.default_factory is not dataclasses.MISSING else None


def default_differences(base: type, derived: type) -> list[str]:
    """Table rows of the fields whose default (or type) ``derived`` changes from ``base``."""
    hints_base, hints_derived = typing.get_type_hints(base), typing.get_type_hints(derived)
    derived_fields = {f.name: f for f in dataclasses.fields(derived)}
    rows = []
    for f in dataclasses.fields(base):
        other = derived_fields[f.name]
        if _default(f) != _default(other) or hints_base[f.name] != hints_derived[f.name]:
            rows.append(f"| `{f.name}` | `{_toml_value(_default(f))}` | `{_toml_value(_default(other))}` |")
    return rows


def config_page(title: str, intro: str, tables: list[tuple[str, str]]) -> str:
    """A reference page of config keys, one section per TOML table."""
    lines = [f"# {title}", "", intro, "", "Generated from the config dataclasses' docstrings.", ""]
    for table, dotted in tables:
        cls = _import(dotted)
        lines += [f"<!-- {dotted} -->", ""]
        lines += _table_sections(cls, table)
        base = next((b for b in cls.__mro__[1:] if dataclasses.is_dataclass(b)), None)
        if base is not None:
            lines += [
                f"## `[{table}]` defaults of `{base.__name__}`",
                "",
                f"`{cls.__name__}` above adds to `{base.__name__}` and changes these defaults:",
                "",
                f"| key | `{base.__name__}` | `{cls.__name__}` |",
                "| --- | --- | --- |",
                *default_differences(base, cls),
                "",
            ]
    return "\n".join(lines)


def generate_pages() -> dict[str, str]:
    """Path under the docs directory -> Markdown text of every generated reference page."""
    if str(REPO) not in sys.path:
        sys.path.insert(0, str(REPO))
    pages = {f"ref/{prog}.md": cli_page(prog) for prog in PROGRAMS}
    for path, (title, intro, tables) in CONFIGS.items():
        pages[path] = config_page(title, intro, tables)
    return pages


# ---------------------------------------------------------------- MkDocs hook


def on_files(files: Any, config: Any) -> Any:
    """MkDocs hook: add the generated pages to the build, and the repository's CHANGELOG.md."""
    from mkdocs.structure.files import File

    for path, text in generate_pages().items():
        files.append(File.generated(config, path, content=text))
    files.append(File.generated(config, "changelog.md", content=(REPO / "CHANGELOG.md").read_text()))
    return files


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Write the generated reference pages to a directory.")
    parser.add_argument("out", type=Path, help="directory to write ref/*.md into")
    args = parser.parse_args(argv)
    for path, text in generate_pages().items():
        target = args.out / path
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(text)
        print(target)
    return 0


if __name__ == "__main__":
    sys.exit(main())
