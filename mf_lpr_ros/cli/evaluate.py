"""Commands that measure: evaluate, compare, slam-eval, suite."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from mf_lpr_ros.cli.common import (
    METHOD_KEYS,
    SOURCE_HELP,
    add_common,
    add_scheduler,
    cluster,
    config_from_arguments,
)
from mf_lpr_ros.datasets import open_source
from mf_lpr_ros.evaluation.methods import METHODS
from mf_lpr_ros.evaluation.suite import DEFAULT_METHODS, write_json_atomic


def _protocol_arguments(args: argparse.Namespace) -> dict:
    return dict(exclude_recent_frames=args.exclude_recent_frames,
                exclude_recent_s=args.exclude_recent_s, query_every=args.query_every,
                query_spacing_m=args.query_spacing_m, progress=not args.quiet)


def cmd_evaluate(args: argparse.Namespace) -> int:
    from mf_lpr_ros.evaluation.protocol import evaluate

    config = config_from_arguments(args)
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
                "candidate_recall", "rte_mean_m", "rre_mean_deg", "success_rate", "f1_max",
                "closures_published", "closures_false", "precision_published",
                "recall_published", "recall_at_100_precision", "ms_per_query"):
        value = results[key]
        print(f"{key:>22}: {value:.4f}" if isinstance(value, float) else f"{key:>22}: {value}")
    if results["queries_not_described"]:
        print(f"{'queries_not_described':>22}: {results['queries_not_described']} (each a miss; "
              f"the records' reason says why)")
    if results["references_not_described"]:
        print(f"{'references_not_described':>22}: {results['references_not_described']} (left "
              f"out of the map; a query at their place misses)")
    return 0


def cmd_compare(args: argparse.Namespace) -> int:
    from mf_lpr_ros.evaluation.protocol import evaluate
    from mf_lpr_ros.evaluation.suite import format_table

    config = config_from_arguments(args)
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

    config = config_from_arguments(args)
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
    from mf_lpr_ros.evaluation.benchmarks import SUITES
    from mf_lpr_ros.evaluation.suite import format_table, run_suite

    if args.list or not args.name:
        for name, suite in SUITES.items():
            print(f"{name:>18}: {suite.description}")
        return 0
    if args.name not in SUITES:
        raise ValueError(f"unknown suite {args.name!r}; choose one of {sorted(SUITES)}")
    if not args.root:
        raise ValueError("suite needs --root, the folder holding the preset's sequences")
    with cluster(args) as client:
        rows = run_suite(SUITES[args.name], Path(args.root), Path(args.out),
                         methods=args.methods, progress=not args.quiet, client=client)
    print(format_table(rows))
    print(f"\nwrote {args.out}/results.csv, results.json, table.md and figures")
    return 0


def cmd_suite_diff(args: argparse.Namespace) -> int:
    from mf_lpr_ros.evaluation.tuning_rule import compare_runs, format_comparison

    comparison = compare_runs(Path(args.before), Path(args.after))
    print(format_comparison(comparison))
    return 0 if comparison.passes or not args.check else 1


def register(commands: argparse._SubParsersAction) -> None:
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
        add_common(evaluation)
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
    add_common(slam)
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
    add_scheduler(suite)
    suite.add_argument("--quiet", action="store_true", help="no progress bars")
    suite.set_defaults(handler=cmd_suite)
    diff = commands.add_parser(
        "suite-diff", help="two runs of a suite before -> after, judged by the tuning rule",
        description="Reads two `mf-lpr suite` output folders (before and after a change) and "
                    "prints the before -> after table docs/RESULTS.md keeps, the share of "
                    "positive queries matched to the same reference, and the tuning rule's "
                    "verdict: the suite's mean (recall@1, corrected recall@1, recall published "
                    "over every pair) rises, no recall drops by more than a point on any pair, "
                    "no false closure is added. Runs of `sensors`, which checks a change rather "
                    "than choosing it, get that suite's verdict instead: no drop of more than a "
                    "point, no false closure added, and auto within a point of default's "
                    "recall@1 on every sensor; the mean need not rise.")
    diff.add_argument("before", help="the suite's output folder before the change")
    diff.add_argument("after", help="the suite's output folder after the change")
    diff.add_argument("--check", action="store_true",
                      help="exit 1 when the change does not pass the rule")
    diff.set_defaults(handler=cmd_suite_diff)
