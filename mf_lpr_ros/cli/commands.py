"""mf-lpr: offline tools for building maps, localising, evaluating and a self-contained demo.

Run `mf-lpr SUBCOMMAND --help` for each tool's options.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import json
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from mf_lpr_ros.config import PRESET_NAMES, Config, load_config, preset
from mf_lpr_ros.errors import ConfigError
from mf_lpr_ros.errors import DatasetError
from mf_lpr_ros.datasets import open_source
from mf_lpr_ros.errors import InvalidCloudError
from mf_lpr_ros.errors import UnitFailure
from mf_lpr_ros.evaluation.methods import METHODS
from mf_lpr_ros.errors import MapFileError
from mf_lpr_ros.core.map_store import ReferenceMap
from mf_lpr_ros.errors import MissingDependencyError
from mf_lpr_ros.evaluation.suite import DEFAULT_METHODS, write_json_atomic

METHOD_KEYS = sorted(METHODS)
SOURCE_HELP = ("a KITTI folder (velodyne/*.bin + poses.txt), a PCD/PLY folder (+ poses_tum.txt "
               "or poses.txt), an NCLT session, an Oxford Radar RobotCar session, a Wild-Places "
               "sequence, a MulRan sequence, a BEV PNG folder (imgs/ + poses.txt) or a ROS 1/2 "
               "bag")


def _config(args: argparse.Namespace) -> Config:
    base = preset(args.preset)
    if getattr(args, "config", None):
        base = load_config(args.config, base)
    if getattr(args, "spacing_m", None) is not None:
        base = replace(base, spacing_m=args.spacing_m)
    if getattr(args, "max_shift_m", None) is not None:
        base = replace(base, search=replace(base.search, max_shift_m=args.max_shift_m))
    return base


def _add_scheduler(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scheduler", help="run the work units on Dask distributed: 'local' "
                        "(a cluster of processes on this machine) or a scheduler ADDRESS "
                        "(tcp://host:8786); default: serial")
    parser.add_argument("--workers", type=int, default=2,
                        help="with --scheduler local: worker processes (default 2)")


def _add_common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--preset", default="default", choices=PRESET_NAMES,
                        help="parameter preset; auto derives the descriptor from the scans "
                             "(voxel size, height band, field of view; default: %(default)s)")
    parser.add_argument("--config", help="YAML file overriding the preset (see config/)")
    parser.add_argument("--cloud-topic", help="PointCloud2 topic of a bag (default: the only one)")
    parser.add_argument("--pose-topic", help="Odometry/PoseStamped topic of a bag (default: the only one)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def cmd_build_map(args: argparse.Namespace) -> int:
    from mf_lpr_ros.pipeline.mapping import build_map

    config = _config(args)
    if args.global_map:
        return _build_global_map(args, config)
    if args.sources:
        return _build_maps(args, config)
    if not args.source:
        raise ValueError("build-map needs a SOURCE (scans with poses), --sources A B ... or "
                         "--global-map CLOUD")
    sequence = open_source(args.source, args.cloud_topic, args.pose_topic)
    reference_map = build_map(sequence, config, keep_clouds=args.keep_clouds,
                              progress=not args.quiet)
    reference_map.save(args.out)
    if "auto" in reference_map.metadata:
        print(reference_map.metadata["auto"]["choice"])
    print(f"wrote {args.out}: {len(reference_map)} references from {len(sequence)} scans "
          f"(voxel {reference_map.params.voxel_size} m, spacing {config.spacing_m} m)")
    return 0


@contextlib.contextmanager
def _cluster(args: argparse.Namespace):
    """The Dask client --scheduler asks for, or None (serial)."""
    if not getattr(args, "scheduler", None):
        yield None
        return
    from mf_lpr_ros.pipeline.distributed import dask_client

    with dask_client(args.scheduler, args.workers) as client:
        yield client


def _build_maps(args: argparse.Namespace, config: Config) -> int:
    from mf_lpr_ros.pipeline.bulk import SourceSpec, build_maps

    if args.source:
        raise ValueError("give the sources either as SOURCE or as --sources, not both")
    specs = [SourceSpec(path, args.cloud_topic, args.pose_topic) for path in args.sources]
    with _cluster(args) as client:
        maps = build_maps(specs, config, combine=not args.one_map_each,
                          keep_clouds=args.keep_clouds, client=client, progress=not args.quiet)
    if args.one_map_each:
        out_dir = Path(args.out)
        out_dir.mkdir(parents=True, exist_ok=True)
        for spec, reference_map in zip(specs, maps):
            path = out_dir / f"{Path(spec.path).name}.mfmap"
            reference_map.save(path)
            print(f"wrote {path}: {len(reference_map)} references")
    else:
        maps[0].save(args.out)
        print(f"wrote {args.out}: {len(maps[0])} references from {len(specs)} sources")
    return 0


def _build_global_map(args: argparse.Namespace, config: Config) -> int:
    from mf_lpr_ros.pipeline.global_map import RenderParams, build_global_map, read_trajectory

    trajectory = read_trajectory(args.trajectory) if args.trajectory else None
    render = RenderParams(spacing_m=args.spacing_m or RenderParams.spacing_m,
                          sensor_height_m=args.sensor_height_m,
                          horizontal_fov_deg=args.horizontal_fov_deg)
    reference_map = build_global_map(args.global_map, config, trajectory=trajectory,
                                     render=render, progress=not args.quiet)
    reference_map.save(args.out)
    area = reference_map.metadata["grid_area_km2"]
    print(f"wrote {args.out}: {len(reference_map)} references rendered from {args.global_map} "
          f"on a {render.spacing_m} m grid over {area:.4f} km^2 (sensor "
          f"{reference_map.metadata['sensor_height_m']:.2f} m above the ground, voxel "
          f"{reference_map.params.voxel_size} m)")
    return 0


def cmd_accumulate(args: argparse.Namespace) -> int:
    from mf_lpr_ros.pipeline.global_map import accumulate, write_pcd

    sequence = open_source(args.source, args.cloud_topic, args.pose_topic)
    cloud = accumulate(sequence, args.voxel, progress=not args.quiet)
    write_pcd(args.out, cloud)
    print(f"wrote {args.out}: {len(cloud)} points from {len(sequence)} scans "
          f"(one per {args.voxel} m voxel)")
    return 0


def cmd_localise(args: argparse.Namespace) -> int:
    from mf_lpr_ros.pipeline.localise import localise_sequence

    reference_map = ReferenceMap.load(args.map)
    search = _config(args).search
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
            writer.writerow([
                outcome.index, f"{outcome.stamp:.6f}", match.reference_index,
                f"{reference_map.stamps[match.reference_index]:.6f}", f"{match.score:.6g}",
                f"{match.confidence:.4f}", int(outcome.verdict.accepted),
                *(f"{v:.4f}" for v in match.pose), *(f"{v:.4f}" for v in truth),
                f"{outcome.translation_error_m:.4f}", f"{outcome.yaw_error_deg:.3f}",
                f"{outcome.descriptor_ms:.2f}", f"{match.timings_ms['global']:.2f}",
                f"{match.timings_ms['local']:.2f}", outcome.verdict.reason])
    errors = np.array([o.translation_error_m for o in outcomes])
    print(f"wrote {args.out}: {len(outcomes)} queries against {len(reference_map)} references"
          + (f"; median translation error {np.nanmedian(errors):.3f} m"
             if np.isfinite(errors).any() else ""))
    return 0


def _protocol_arguments(args: argparse.Namespace) -> dict:
    return dict(exclude_recent_frames=args.exclude_recent_frames,
                exclude_recent_s=args.exclude_recent_s, query_every=args.query_every,
                query_spacing_m=args.query_spacing_m, progress=not args.quiet)


def cmd_evaluate(args: argparse.Namespace) -> int:
    from mf_lpr_ros.evaluation.protocol import evaluate

    config = _config(args)
    reference = open_source(args.reference, args.cloud_topic, args.pose_topic)
    query = open_source(args.query, args.cloud_topic, args.pose_topic) if args.query else None
    results = evaluate(reference, config, args.tolerance, query=query, method=args.method,
                       **_protocol_arguments(args))
    results["config"] = config.to_dict()
    if "auto" in results:
        print(results["auto"]["choice"])
    text = json.dumps(results, indent=2)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(text + "\n")
    for key in ("n_queries", "n_references", "recall_at_1", "recall_at_1_corrected", "recall_at_5",
                "rte_mean_m", "rre_mean_deg", "success_rate", "f1_max", "closures_published",
                "closures_false", "precision_published", "recall_published",
                "recall_at_100_precision", "ms_per_query"):
        value = results[key]
        print(f"{key:>22}: {value:.4f}" if isinstance(value, float) else f"{key:>22}: {value}")
    return 0


def cmd_compare(args: argparse.Namespace) -> int:
    from mf_lpr_ros.evaluation.protocol import evaluate
    from mf_lpr_ros.evaluation.suite import format_table

    config = _config(args)
    reference = open_source(args.reference, args.cloud_topic, args.pose_topic)
    query = open_source(args.query, args.cloud_topic, args.pose_topic) if args.query else None
    results = {}
    for method in args.methods:
        summary = evaluate(reference, config, args.tolerance, query=query, method=method,
                           **_protocol_arguments(args))
        results[METHODS[method].name] = summary
    first = next(iter(results.values()))
    print(f"\n{reference.name}: {first['n_queries']} revisit queries of {first['n_evaluated']}, "
          f"{first['n_references']} references, tolerance {args.tolerance} m, preset "
          f"{args.preset}\n")
    print(format_table([{"pair": reference.name, "method": name, **values}
                        for name, values in results.items()]))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"config": config.to_dict(),
                                               "tolerance_m": args.tolerance,
                                               "results": results}, indent=2) + "\n")
    return 0


def cmd_slam_eval(args: argparse.Namespace) -> int:
    from mf_lpr_ros.evaluation.protocol import Protocol
    from mf_lpr_ros.evaluation.slam import DriftModel, slam_eval, slam_figure

    config = _config(args)
    sequence = open_source(args.reference, args.cloud_topic, args.pose_topic)
    protocol = Protocol(args.tolerance, query_every=args.query_every,
                        exclude_recent_frames=args.exclude_recent_frames,
                        exclude_recent_s=args.exclude_recent_s)
    drift = DriftModel(scale_error=args.drift_scale_error,
                       yaw_bias_deg_per_m=args.drift_yaw_bias_deg_per_m, seed=args.drift_seed)
    result = slam_eval(sequence, config, protocol, drift=drift, progress=not args.quiet)
    result["config"] = config.to_dict()
    if args.json:
        write_json_atomic(Path(args.json), result)
    if args.figure:
        slam_figure(result, args.figure)
    for key in ("n_keyframes", "path_length_m", "ate_odometry_m", "ate_optimised_m",
                "closures_published", "closures_false", "closures_used", "closures_false_used",
                "recall_published"):
        value = result[key]
        print(f"{key:>20}: {value:.4f}" if isinstance(value, float) else f"{key:>20}: {value}")
    return 0


def cmd_suite(args: argparse.Namespace) -> int:
    from mf_lpr_ros.evaluation.suite import SUITES, format_table, run_suite

    if args.list or not args.name:
        for name, suite in SUITES.items():
            print(f"{name:>18}: {suite.description}")
        return 0
    if args.name not in SUITES:
        raise ValueError(f"unknown suite {args.name!r}; choose one of {sorted(SUITES)}")
    if not args.root:
        raise ValueError("suite needs --root, the folder holding the preset's sequences")
    with _cluster(args) as client:
        rows = run_suite(SUITES[args.name], Path(args.root), Path(args.out),
                         methods=args.methods, progress=not args.quiet, client=client)
    print(format_table(rows))
    print(f"\nwrote {args.out}/results.csv, results.json, table.md and figures")
    return 0


def cmd_info(args: argparse.Namespace) -> int:
    reference_map = ReferenceMap.load(args.map)
    poses = reference_map.planar_poses
    print(json.dumps({
        "references": len(reference_map),
        "descriptor": reference_map.params.__dict__,
        "frame_id": reference_map.frame_id,
        "sensor_frame_id": reference_map.sensor_frame_id,
        "keeps_clouds": reference_map.has_clouds,
        "extent_xy_m": (poses[:, :2].min(0).tolist(), poses[:, :2].max(0).tolist())
        if len(poses) else None,
        "metadata": reference_map.metadata,
    }, indent=2))
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


def cmd_global_demo(args: argparse.Namespace) -> int:
    from mf_lpr_ros.sim import global_demo

    rows, facts = global_demo.run(args.source, progress=not args.quiet)
    print(global_demo.format_table(rows, facts))
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from mf_lpr_ros.ros import demo

    out = Path(args.out)
    if args.data:
        bag = Path(args.data)
        chosen = demo.choose_preset(bag) if args.preset == "auto" else args.preset
        out.mkdir(parents=True, exist_ok=True)
        rows = demo.run_bag_loop_closure(bag, chosen, out / f"{bag.stem}.mfmap", rate=args.rate,
                                         progress=not args.quiet)
        print()
        print(demo.format_rows(rows))
        return 0
    demo.run_demo(out, args.worlds, progress=not args.quiet, stride=args.stride)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mf-lpr", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)

    build = commands.add_parser(
        "build-map", help="build a reference map from a sequence or bag, or render one from a "
        "global point-cloud map (--global-map)")
    build.add_argument("source", nargs="?", help=SOURCE_HELP)
    build.add_argument("--sources", nargs="+", help="many sources: one map of them all at "
                       "--out, or one map each in the folder --out with --one-map-each")
    build.add_argument("--one-map-each", action="store_true",
                       help="with --sources: --out is a folder, one SOURCE_NAME.mfmap per source")
    _add_scheduler(build)
    build.add_argument("--global-map", help="a global map (.pcd/.ply, world frame, z up): "
                       "references rendered on a grid over its traversable area")
    build.add_argument("--trajectory", help="with --global-map: the mapping run's poses (KITTI "
                       "poses.txt or TUM), seeding the area and giving the sensor height")
    build.add_argument("--sensor-height-m", type=float,
                       help="with --global-map: the sensor's height above the ground "
                            "(default: from --trajectory, else 1.8)")
    build.add_argument("--horizontal-fov-deg", type=float, default=360.0,
                       help="with --global-map: the sensor's horizontal field of view; below "
                            "360 (e.g. 70 for a Livox Avia) references face several headings, "
                            "each with only its wedge")
    build.add_argument("--out", required=True, help="map file to write (atomically)")
    build.add_argument("--spacing-m", type=float, help="distance between references (default 2.0)")
    build.add_argument("--keep-clouds", action="store_true",
                       help="store reference clouds in the map (enables ICP refinement)")
    _add_common(build)
    build.set_defaults(handler=cmd_build_map)

    accumulate = commands.add_parser(
        "accumulate", help="a global map (binary PCD) from a posed sequence or bag")
    accumulate.add_argument("source", help=SOURCE_HELP)
    accumulate.add_argument("--out", required=True, help="PCD file to write (atomically)")
    accumulate.add_argument("--voxel", type=float, default=0.2,
                            help="keep one point per voxel of this size, m (default 0.2)")
    accumulate.add_argument("--cloud-topic", help="PointCloud2 topic of a bag")
    accumulate.add_argument("--pose-topic", help="Odometry/PoseStamped topic of a bag")
    accumulate.add_argument("--quiet", action="store_true", help="no progress bars")
    accumulate.set_defaults(handler=cmd_accumulate)

    localise = commands.add_parser("localise", help="match every scan of a source against a map")
    localise.add_argument("map", help="map file from build-map")
    localise.add_argument("source", help=SOURCE_HELP)
    localise.add_argument("--out", required=True, help="CSV with one row per query")
    localise.add_argument("--min-confidence", type=float, help="accept threshold for the CSV")
    localise.add_argument("--max-shift-m", type=float, help="largest searched translation")
    localise.add_argument("--icp", action="store_true",
                          help="refine each pose by ICP (open3d) against the map's reference clouds")
    _add_common(localise)
    localise.set_defaults(handler=cmd_localise)

    protocol_help = ("With --query: references from --reference, queries from --query. Without: "
                     "the single-sequence loop-closure protocol (each scan queries the references "
                     "more than --exclude-recent-frames frames older).")
    for name, handler, text in (
            ("evaluate", cmd_evaluate, "recall, pose errors and timings against ground truth"),
            ("compare", cmd_compare, "MF-LPR and the baselines side by side, same data and "
                                     "protocol")):
        evaluation = commands.add_parser(name, help=text, description=protocol_help)
        evaluation.add_argument("--reference", required=True, help=SOURCE_HELP)
        evaluation.add_argument("--query", help="a second source of queries")
        evaluation.add_argument("--tolerance", type=float, required=True,
                                help="metres within which a match counts as correct")
        evaluation.add_argument("--exclude-recent-frames", type=int, default=0)
        evaluation.add_argument("--exclude-recent-s", type=float, default=0.0,
                                help="references must be this many seconds older than the query")
        evaluation.add_argument("--query-every", type=int, default=1,
                                help="use every N-th scan as query")
        evaluation.add_argument("--query-spacing-m", type=float, default=0.0,
                                help="one query per this many metres of travel (0: every scan)")
        evaluation.add_argument("--spacing-m", type=float,
                                help="distance between references (default 2.0)")
        evaluation.add_argument("--max-shift-m", type=float, help="largest searched translation")
        evaluation.add_argument("--json", help="write the results here")
        if name == "evaluate":
            evaluation.add_argument("--method", default="mf-lpr", choices=METHOD_KEYS)
        else:
            evaluation.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS),
                                    choices=METHOD_KEYS,
                                    help="methods to compare (default: %(default)s; "
                                         "map-closures needs the map-closures package)")
        _add_common(evaluation)
        evaluation.set_defaults(handler=handler)

    slam = commands.add_parser(
        "slam-eval", help="loop closures in a GTSAM pose graph: trajectory error before/after",
        description="Drifts the ground-truth odometry of --reference (a documented, seeded "
                    "model), finds and verifies loop closures on it exactly as the localiser "
                    "does (the single-sequence protocol), optimises a GTSAM pose graph, and "
                    "reports ATE (RMSE after rigid alignment) of the odometry and the optimised "
                    "trajectory. Needs gtsam (pip install gtsam).")
    slam.add_argument("--reference", required=True, help=SOURCE_HELP)
    slam.add_argument("--tolerance", type=float, required=True,
                      help="metres beyond which a closure counts as false")
    slam.add_argument("--exclude-recent-frames", type=int, default=100)
    slam.add_argument("--exclude-recent-s", type=float, default=0.0)
    slam.add_argument("--query-every", type=int, default=1, help="every N-th scan queries")
    slam.add_argument("--spacing-m", type=float, help="distance between references (default 2.0)")
    slam.add_argument("--drift-scale-error", type=float, default=0.01,
                      help="odometry scale error (default %(default)s)")
    slam.add_argument("--drift-yaw-bias-deg-per-m", type=float, default=0.003,
                      help="odometry heading bias (default %(default)s)")
    slam.add_argument("--drift-seed", type=int, default=0)
    slam.add_argument("--json", help="write the results here (atomically)")
    slam.add_argument("--figure", help="PNG of ground truth, odometry and optimised trajectory")
    _add_common(slam)
    slam.set_defaults(handler=cmd_slam_eval)

    suite = commands.add_parser(
        "suite", help="a benchmark preset: every pair, every method, CSV + JSON + figures",
        description="Runs a named benchmark (the paper's dataset pairs and protocol) over the "
                    "sequences under --root, with a progress bar. Each finished pair is saved "
                    "at once, so an interrupted run resumes where it stopped. Writes "
                    "results.csv, results.json, table.md and figures under --out.")
    suite.add_argument("name", nargs="?", help="benchmark preset (see --list)")
    suite.add_argument("--root", help="dataset root holding the preset's sequences")
    suite.add_argument("--out", default="out/suite", help="output folder (default: %(default)s)")
    suite.add_argument("--methods", nargs="+", choices=METHOD_KEYS,
                       help=f"methods (default: {' '.join(DEFAULT_METHODS)})")
    suite.add_argument("--list", action="store_true", help="list the presets and exit")
    _add_scheduler(suite)
    suite.add_argument("--quiet", action="store_true", help="no progress bars")
    suite.set_defaults(handler=cmd_suite)

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

    info = commands.add_parser("info", help="describe a map file")
    info.add_argument("map")
    info.set_defaults(handler=cmd_info)

    global_demo = commands.add_parser(
        "global-demo", help="relocalising off the mapping path in the simulator: a keyframe "
        "map against a grid rendered from the global map (mf_lpr_ros/global_demo.py)")
    global_demo.add_argument("--source", default="drive", choices=["drive", "world"],
                             help="the global cloud: the mapping drive's scans accumulated "
                                  "(default), or the whole world's surfaces")
    global_demo.add_argument("--quiet", action="store_true", help="no progress bars")
    global_demo.set_defaults(handler=cmd_global_demo)

    demo = commands.add_parser(
        "demo", help="the whole system on simulated worlds, or on a real bag, through the nodes",
        description="Simulates urban and forest worlds (two days each, written as ROS 2 bags under "
                    "--out and reused), streams day 1 through map_builder and day 2 through the "
                    "localiser over DDS, and prints recall, pose errors, rejection of unseen "
                    "places and latency, with a figure. With --data BAG: map_builder and the "
                    "localiser in loop_closure mode on one replay of a real bag.")
    demo.add_argument("--out", default="out/demo", help="folder for bags, maps and the figure")
    demo.add_argument("--worlds", nargs="+", default=["urban", "forest"],
                      choices=["urban", "forest"])
    demo.add_argument("--stride", type=int, default=1,
                      help="keep every N-th simulated scan (a quicker demo)")
    demo.add_argument("--data", help="a real bag with PointCloud2 and poses (loop_closure mode)")
    demo.add_argument("--preset", default="auto", help="with --data: a preset, or auto "
                      "(handheld for close-range scans, else kitti)")
    demo.add_argument("--rate", type=float, default=1.0, help="with --data: replay speed-up")
    demo.add_argument("--quiet", action="store_true")
    demo.set_defaults(handler=cmd_demo)
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
