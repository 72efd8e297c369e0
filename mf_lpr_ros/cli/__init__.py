"""mf-lpr: offline tools for building maps, localising, evaluating and a self-contained demo.

Run `mf-lpr SUBCOMMAND --help` for each tool's options. One module per command group:
cli.maps, cli.localise, cli.evaluate, cli.demos, cli.presets, cli.reference_docs.
"""

from __future__ import annotations

import argparse
import sys

from mf_lpr_ros.cli import demos, evaluate, localise, maps, presets, reference_docs
from mf_lpr_ros.errors import (
    ConfigError,
    DatasetError,
    InvalidCloudError,
    MapFileError,
    MissingDependencyError,
    UnitFailure,
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mf-lpr", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    for group in (maps, localise, evaluate, demos, presets, reference_docs):
        group.register(commands)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.handler(args)
    except (ConfigError, DatasetError, MapFileError, InvalidCloudError, MissingDependencyError,
            UnitFailure, ValueError) as error:
        print(f"mf-lpr {args.command}: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
