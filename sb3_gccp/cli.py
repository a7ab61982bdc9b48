"""The ``sb3_gccp`` command line.

It dispatches to one module per command (:mod:`sb3_gccp.commands`): ``rollout`` (the scripted
hierarchy), ``train`` (a training stage), ``evaluate`` (a hierarchy or a baseline on seeded traffic),
``video`` (one episode), ``reproduce`` (the paper's tables and figures), ``tune`` (a hyperparameter
search), ``export`` (a run as a small folder) and ``config`` (the world config keys). Errors in the
input are reported on one line and exit with status 2.
"""

from __future__ import annotations

import argparse
import sys
from typing import NoReturn

from sb3_gccp.commands import config, evaluate, export, reproduce, rollout, train, tune, video
from sb3_gccp.commands.common import CLIError

COMMANDS = (rollout, train, evaluate, video, reproduce, tune, export, config)
"""The command modules, in the order ``--help`` lists them."""


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line, as the commands' own input errors are (its
    sub-command parsers are of its class too)."""

    def error(self, message: str) -> NoReturn:
        """Exit with status 2 and one line naming the problem, instead of the usage block and the line."""
        self.exit(2, f"sb3_gccp: error: {message} (see `{self.prog} --help`)\n")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``sb3_gccp``."""
    parser = OneLineParser(prog="sb3_gccp", description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        command.add_parser(commands)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``sb3_gccp``."""
    args = build_parser().parse_args(argv)
    try:
        args.func(args)
    except CLIError as err:
        print(f"sb3_gccp: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("sb3_gccp: interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
