"""What the command groups share: the config from --preset/--config, common options, Dask."""

from __future__ import annotations

import argparse
import contextlib
from dataclasses import replace

from mf_lpr_ros.config import PRESET_NAMES, Config, load_config, preset
from mf_lpr_ros.datasets import LOADERS
from mf_lpr_ros.evaluation.methods import METHODS

METHOD_KEYS = sorted(METHODS)
SOURCE_HELP = "; ".join(loader.layout for loader in LOADERS) + " (docs/DATASETS.md)"


def config_from_arguments(args: argparse.Namespace) -> Config:
    base = preset(args.preset)
    if getattr(args, "config", None):
        base = load_config(args.config, base)
    if getattr(args, "spacing_m", None) is not None:
        base = replace(base, spacing_m=args.spacing_m)
    if getattr(args, "max_shift_m", None) is not None:
        base = replace(base, search=replace(base.search, max_shift_m=args.max_shift_m))
    return base


def add_scheduler(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scheduler", help="run the work units (with build-map --global-map: "
                        "the rendering) on Dask distributed: 'local' (a cluster of processes "
                        "on this machine) or a scheduler ADDRESS (tcp://host:8786); default: no "
                        "cluster")
    parser.add_argument("--workers", type=int, default=2,
                        help="with --scheduler local: worker processes; with build-map "
                        "--global-map: rendering processes (default 2)")


def add_common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--preset", default="default", choices=PRESET_NAMES,
                        help="parameter preset; auto derives the descriptor from the scans "
                             "(voxel size, height band, field of view; default: %(default)s)")
    parser.add_argument("--config", help="YAML file overriding the preset (see config/)")
    parser.add_argument("--cloud-topic", help="PointCloud2 topic of a bag (default: the only one)")
    parser.add_argument("--pose-topic",
                        help="Odometry/PoseStamped topic of a bag (default: the only one)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


@contextlib.contextmanager
def cluster(args: argparse.Namespace):
    """The Dask client --scheduler asks for, or None (serial)."""
    if not getattr(args, "scheduler", None):
        yield None
        return
    from mf_lpr_ros.pipeline.distributed import dask_client

    with dask_client(args.scheduler, args.workers) as client:
        yield client
