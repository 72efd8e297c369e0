"""The presets command: list the named presets, or write them out as config/*.yaml."""

from __future__ import annotations

import argparse
from pathlib import Path

from mf_lpr_ros.config import PRESETS, write_preset_files


def cmd_presets(args: argparse.Namespace) -> int:
    if args.write:
        for path in write_preset_files(Path(args.write)):
            print(f"wrote {path}")
        return 0
    print("\n".join(sorted(PRESETS)))
    return 0


def register(commands: argparse._SubParsersAction) -> None:
    presets = commands.add_parser(
        "presets", help="list the parameter presets, or write them as ROS 2 parameter files",
        description="The presets are defined in mf_lpr_ros/config.py; config/*.yaml are generated "
                    "from them with `mf-lpr presets --write config` (a test checks they agree).")
    presets.add_argument("--write", metavar="FOLDER",
                         help="write FOLDER/<preset>.yaml for every named preset")
    presets.set_defaults(handler=cmd_presets)
