"""Shared shape of the three command-line fronts (avoid-companion, avoid-sim, avoid-train).

Each subcommand lives in its own module, which provides ``configure_parser(parser)`` and
``command(args) -> int``. A :class:`UserError` becomes a one-line message and exit status 2,
never a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from companion.common.errors import UserError

#: every command line's log lines (the demo's flight processes set up the same)
LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def run_cli(
    prog: str, description: str, subcommands: dict[str, tuple[str, str]], argv: list[str] | None
) -> int:
    """Parse ``argv`` and run the chosen subcommand.

    :param prog: program name shown in usage and error lines
    :param description: one-line description for ``--help``
    :param subcommands: name -> (module path, one-line help)
    :param argv: arguments (``None``: ``sys.argv[1:]``)
    """
    parser = argparse.ArgumentParser(prog=prog, description=description)
    parser.add_argument("-v", "--verbose", action="store_true", help="log debug messages")
    sub = parser.add_subparsers(dest="subcommand", metavar="COMMAND", required=True)
    for name, (module_name, help_text) in subcommands.items():
        module = importlib.import_module(module_name)
        p = sub.add_parser(name, help=help_text, description=help_text)
        module.configure_parser(p)
        p.set_defaults(_module=module)
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format=LOG_FORMAT,
    )
    try:
        return int(args._module.command(args))
    except UserError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
