"""``sb3_gccp export``: a trained run as a small folder that evaluates on its own (like ``pretrained/``)."""

from __future__ import annotations

import argparse

from sb3_gccp.commands.common import (
    CLIError,
    add_mask_overrides,
    add_trust_pickle,
    add_world_overrides,
    parse_assignments,
)


def add_parser(commands: argparse._SubParsersAction) -> None:
    """Declare the command and its options."""
    parser = commands.add_parser(
        "export", help="copy a trained run into a small folder that evaluates on its own (like pretrained/)"
    )
    parser.add_argument("run", help="a decider run folder (hierarchy.yml) or a baseline run folder")
    parser.add_argument("out", help="a new (or empty) folder")
    add_world_overrides(parser)
    add_mask_overrides(parser)
    add_trust_pickle(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> None:
    """Export the run and print what was written."""
    from sb3_gccp.export import export_run

    try:
        written = export_run(
            args.run,
            args.out,
            parse_assignments(args.set),
            parse_assignments(args.mask, "--mask"),
            args.trust_pickle,
        )
    except (ValueError, TypeError, OSError) as err:
        raise CLIError(str(err)) from err
    size = sum(path.stat().st_size for path in written)
    print(f"exported {args.run} to {args.out}: {len(written)} files, {size / 1e6:.1f} MB")
