"""What several commands share: one-line input errors, ``KEY=VALUE`` options, the world config and
output paths checked before the work starts."""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml

from gccp_envs import config as world_config
from gccp_envs.config import IntersectionConfig
from sb3_gccp.gccp.settings import CHECK_KEYS


class CLIError(Exception):
    """A problem with the command's input, reported on one line."""


def load_world_config(path: str | None, assignments: list[str]) -> IntersectionConfig:
    """The world config from an optional YAML file of config keys plus ``KEY=VALUE`` overrides.

    Values of ``--set`` are read as YAML scalars or lists (``task=left``, ``spawn_probability=0.1``).
    """
    from sb3_gccp.hyperparams import HyperparamsError, read_yaml_mapping

    values: dict[str, Any] = {}
    if path is not None:
        try:
            values.update(read_yaml_mapping(path, "config file"))
        except HyperparamsError as err:
            raise CLIError(str(err)) from err
    values.update(parse_assignments(assignments))
    try:
        return IntersectionConfig.from_dict(values)
    except (ValueError, TypeError) as err:
        raise CLIError(str(err)) from err


def parse_assignments(assignments: list[str], flag: str = "--set") -> dict[str, Any]:
    """``KEY=VALUE`` strings (of option ``flag``) as a mapping, values read as YAML scalars or lists."""
    values: dict[str, Any] = {}
    for item in assignments:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise CLIError(f"{flag} expects KEY=VALUE, got {item!r}")
        try:
            values[key.strip()] = yaml.safe_load(raw)
        except yaml.YAMLError as err:
            raise CLIError(
                f"{flag} {item!r}: the value is not valid YAML ({str(err).splitlines()[0]})"
            ) from err
    return values


def seed_value(text: str) -> int:
    """A seed given on the command line (an argparse ``type``): a whole number, 0 or more, as gymnasium and
    numpy take them."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a seed is a whole number >= 0, got {text!r}") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"a seed is a whole number >= 0, got {value}")
    return value


def parse_tasks(text: str) -> list[str]:
    """Comma-separated task names, validated (see :func:`gccp_envs.config.parse_tasks`)."""
    try:
        return world_config.parse_tasks(text)
    except ValueError as err:
        raise CLIError(str(err)) from err


def check_output_path(path: str | None, flag: str) -> None:
    """Fail before any work, with a one-line reason, if the file of option ``flag`` could not be written.

    :param path: the file asked for (None: the option was not given)
    """
    if path is None:
        return
    folder = Path(path).parent
    if not folder.is_dir():
        raise CLIError(f"{flag} {path}: no folder {folder}")
    if Path(path).is_dir() or not os.access(folder, os.W_OK):
        raise CLIError(f"{flag} {path}: not writable")


def write_results(path: str, table: dict[str, dict[str, float]], episodes: Sequence[Any]) -> None:
    """The ``--json`` file of ``rollout`` and ``evaluate``: the table and every episode."""
    Path(path).write_text(
        json.dumps({"table": table, "episodes": [dataclasses.asdict(r) for r in episodes]}, indent=2)
    )


def add_world_options(parser: argparse.ArgumentParser) -> None:
    """``--config FILE`` and ``--set KEY=VALUE``: the world config of a command that builds one."""
    parser.add_argument("--config", help="YAML file of world config keys (see `sb3_gccp config`)")
    add_world_overrides(parser)


def add_world_overrides(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """``--set KEY=VALUE`` (repeatable): world config keys replacing a trained model's."""
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a world config key (repeatable)",
    )


def add_mask_overrides(parser: argparse.ArgumentParser) -> None:
    """``--mask KEY=VALUE`` (repeatable): GCCP check settings replacing a trained hierarchy's."""
    parser.add_argument(
        "--mask",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a GCCP check setting of hierarchy.yml (repeatable): " + ", ".join(CHECK_KEYS),
    )


def add_allow_overrides(parser: argparse.ArgumentParser) -> None:
    """``--allow-overrides``: run a hierarchy whose ``hierarchy.yml`` has an ``overrides`` section."""
    parser.add_argument(
        "--allow-overrides",
        action="store_true",
        help="run the overrides section of hierarchy.yml (settings the decider was not trained with)",
    )


def add_trust_pickle(parser: argparse.ArgumentParser) -> None:
    """``--trust-pickle``: load models through SB3's ``load``, which runs code pickled in the files."""
    parser.add_argument(
        "--trust-pickle",
        action="store_true",
        help="load the .zip files with SB3's load(), which runs code pickled in them: only for files you "
        "trust (default: rebuild the policies from plain data and weights, running nothing from the files)",
    )


def add_torch_threads(parser: argparse.ArgumentParser, whose: str) -> None:
    """``--torch-threads N`` (default 1, as the shipped models were trained): torch threads of ``whose``."""
    parser.add_argument(
        "--torch-threads",
        type=int,
        default=1,
        help=f"torch threads of {whose} (default 1: the networks are small, and the env workers need the "
        "other cores)",
    )
