"""Commands that run against a map or a ROS graph: localise, replay."""

from __future__ import annotations

import argparse
import csv
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from mf_lpr_ros.cli.common import SOURCE_HELP, add_common, config_from_arguments
from mf_lpr_ros.core.auto_params import map_built_warning
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.datasets import open_source


def cmd_localise(args: argparse.Namespace) -> int:
    from mf_lpr_ros.pipeline.localise import localise_sequence

    reference_map = ReferenceMap.load(args.map)
    warning = map_built_warning(reference_map.metadata)
    if warning is not None:
        print(f"warning: {warning}", file=sys.stderr)
    search = config_from_arguments(args).search
    if args.min_confidence is not None:
        search = replace(search, min_confidence=args.min_confidence)
    sequence = open_source(args.source, args.cloud_topic, args.pose_topic)
    outcomes = localise_sequence(reference_map, sequence, search, icp=args.icp,
                                 progress=not args.quiet)
    columns = ["index", "stamp", "ref_index", "ref_stamp", "score", "confidence", "accepted", "x",
               "y", "yaw", "gt_x", "gt_y", "gt_yaw", "translation_error_m", "yaw_error_deg",
               "ms_descriptor", "ms_global", "ms_local", "reason"]
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    with open(args.out, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(columns)
        for outcome in outcomes:
            match = outcome.match
            truth = outcome.truth if outcome.truth is not None else np.full(3, math.nan)
            if match is None:
                # A scan with nothing to describe: no match, its columns empty.
                found, pose, stages = ["", "", "", ""], np.full(3, math.nan), ["", ""]
            else:
                found = [match.reference_index,
                         f"{reference_map.stamps[match.reference_index]:.6f}",
                         f"{match.score:.6g}", f"{match.confidence:.4f}"]
                pose = match.pose
                stages = [f"{match.timings_ms[stage]:.2f}" for stage in ("global", "local")]
            writer.writerow([
                outcome.index, f"{outcome.stamp:.6f}", *found, int(outcome.verdict.accepted),
                *(f"{v:.4f}" for v in pose), *(f"{v:.4f}" for v in truth),
                f"{outcome.translation_error_m:.4f}", f"{outcome.yaw_error_deg:.3f}",
                f"{outcome.descriptor_ms:.2f}", *stages, outcome.verdict.reason])
    errors = np.array([o.translation_error_m for o in outcomes])
    not_described = sum(outcome.match is None for outcome in outcomes)
    print(f"wrote {args.out}: {len(outcomes)} queries against {len(reference_map)} references"
          + (f"; median translation error {np.nanmedian(errors):.3f} m"
             if np.isfinite(errors).any() else "")
          + (f"; {not_described} passed over with nothing to describe (their reason column "
             f"says why)" if not_described else ""))
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    from mf_lpr_ros.ros.replay import replay_with_own_context

    report = replay_with_own_context(args.bag, args.ros_args, topics=args.topics, rate=args.rate,
                                     wait_for_subscribers=args.wait_for_subscribers,
                                     wait_timeout_s=args.wait_timeout_s, progress=not args.quiet)
    if report is None:
        return 130
    for topic, count in report.published.items():
        print(f"published {count} messages on {topic}")
    for topic, reason in report.skipped_topics.items():
        print(f"skipped {topic}: {reason}")
    print(f"replayed in {report.seconds:.1f} s")
    return 0


def register(commands: argparse._SubParsersAction) -> None:
    localise = commands.add_parser("localise", help="match every scan of a source against a map")
    localise.add_argument("map", help="map file from build-map")
    localise.add_argument("source", help=SOURCE_HELP)
    localise.add_argument("--out", required=True, help="CSV with one row per query")
    localise.add_argument("--min-confidence", type=float, help="accept threshold for the CSV")
    localise.add_argument("--max-shift-m", type=float, help="largest searched translation")
    localise.add_argument("--icp", action="store_true",
                          help="refine each pose by ICP (open3d) against the map's reference "
                               "clouds")
    add_common(localise)
    localise.set_defaults(handler=cmd_localise)
    replay = commands.add_parser(
        "replay", help="publish a bag's clouds and poses on live ROS 2 topics",
        description="Publishes a ROS 1 (.bag) or ROS 2 (.db3/.mcap) bag with rclpy, paced by the "
                    "bag's timestamps, keeping header stamps. Arguments after --ros-args go to "
                    "rclpy (e.g. --ros-args -r /points:=/velodyne_points).")
    replay.add_argument("bag", help="bag file or ROS 2 bag folder")
    replay.add_argument("--topics", nargs="+", help="topics to publish (default: every "
                        "PointCloud2, Odometry, Pose(WithCovariance)Stamped and /tf topic)")
    replay.add_argument("--rate", type=float, default=1.0, help="speed-up over real time")
    replay.add_argument("--wait-for-subscribers", type=int, default=0, metavar="N",
                        help="start once every topic has N subscribers")
    replay.add_argument("--wait-timeout-s", type=float, default=30.0)
    replay.add_argument("--quiet", action="store_true")
    replay.add_argument("--ros-args", nargs=argparse.REMAINDER, default=[],
                        help="rclpy arguments (remappings, parameters)")
    replay.set_defaults(handler=cmd_replay)
