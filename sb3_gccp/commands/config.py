"""``sb3_gccp config``: every world config key with its value and meaning."""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import itertools
import json

from gccp_envs.config import IntersectionConfig
from sb3_gccp.commands.common import add_world_options, load_world_config


def add_parser(commands: argparse._SubParsersAction) -> None:
    """Declare the command and its options."""
    parser = commands.add_parser("config", help="print the world config keys, values and meanings")
    add_world_options(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> None:
    """Print one line per config key: ``key: value  # meaning``."""
    config = load_world_config(args.config, args.set)
    docs = field_docs()
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        shown = list(value) if isinstance(value, tuple) else value
        print(f"{field.name}: {json.dumps(shown)}  # {docs.get(field.name, '')}")


def field_docs() -> dict[str, str]:
    """The one-line docstring under each config field, read from the source."""
    tree = ast.parse(inspect.getsource(IntersectionConfig))
    body = tree.body[0].body  # type: ignore[attr-defined]
    docs = {}
    for node, following in itertools.pairwise(body):
        if (
            isinstance(node, ast.AnnAssign)
            and isinstance(following, ast.Expr)
            and isinstance(following.value, ast.Constant)
            and isinstance(node.target, ast.Name)
        ):
            docs[node.target.id] = " ".join(str(following.value.value).split())
    return docs
